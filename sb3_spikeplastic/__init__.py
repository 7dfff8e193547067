"""sb3-spikeplastic: spiking plastic policies for Stable-Baselines3."""
__version__ = "0.1.0"
