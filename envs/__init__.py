"""Environments for sb3-sfgpi: multi-objective PettingZoo envs with vector rewards (no dependency on sb3_sfgpi)."""
