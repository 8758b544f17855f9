"""The project's Hydra plugins: the arms sweeper (arms_sweeper.py)."""
