"""Built-in scenarios of the paper's experiments (TOML data files)."""
