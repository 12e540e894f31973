"""Environments for sb3-sfgpi: multi-objective PettingZoo envs with vector rewards (no dependency on sb3_sfgpi)."""

from .four_room import FourRoomParallelEnv

__all__ = ["FourRoomParallelEnv"]
