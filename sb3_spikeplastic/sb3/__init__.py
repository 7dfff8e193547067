"""The Stable-Baselines3 glue: :class:`~sb3_spikeplastic.sb3.policy.SpikePlasticPolicy`, the recurrent
:class:`~sb3_spikeplastic.sb3.ppo.PPO` that carries the network state, its chunked rollout buffer, CUDA graphs,
the rollout's TensorBoard scalars, encoder features for other policies and the plasticity ablations.

Imports only :mod:`sb3_spikeplastic.snn` of the package.
"""
