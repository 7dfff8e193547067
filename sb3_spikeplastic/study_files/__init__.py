"""The studies installed with the package: ``sb3-spikeplastic study fig4`` / ``study reversal`` /
``study tmaze`` (their YAML files)."""
