"""The rl-zoo-style experiment tooling behind the command line: hyperparameter files, runs and their folders,
callbacks, evaluation, recording, figures, ``enjoy`` and ``inspect``.

Imports :mod:`sb3_spikeplastic.snn` and :mod:`sb3_spikeplastic.sb3`, never :mod:`sb3_spikeplastic.study`.
"""
