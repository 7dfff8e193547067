"""The spiking plastic network in plain PyTorch: neurons, plasticity rules, population coding, the plastic layer
(its interval step in ``functional``, the compiled step in ``fused_interval``, the module in ``layers``), the
network, its energy, and the compiled kernels that run them (``_fast``).

The lowest layer: it imports nothing else of the package, so that it can be used without Stable-Baselines3.
"""
