"""sb3-sfgpi: successor features, OLS and GPI for Stable-Baselines3."""
