"""The studies installed with the package: ``sb3-spikeplastic study fig4`` / ``study tmaze`` (their YAML files)."""
