"""The studies installed with the package: ``sb3-spikeplastic study fig4`` / ``study reversal`` / ``study tmaze`` /
``study switch_zero_shot`` / ``study switch_meta`` (their YAML files)."""
