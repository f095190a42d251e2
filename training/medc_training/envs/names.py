"""The names of the paper's applications (no torch: importable by light modules)."""

from __future__ import annotations

TARGET_LOCALIZATION = "target_localization"
FLEET_COORDINATION = "fleet_coordination"
MAZE_CLEANING = "maze_cleaning"
#: The paper's applications, in order; ``medc_training.envs.APPLICATIONS`` holds their descriptors.
ENV_NAMES: tuple[str, ...] = (TARGET_LOCALIZATION, FLEET_COORDINATION, MAZE_CLEANING)
#: The application a run, a plan, a bundle or a node takes when none is named (the primary one).
DEFAULT_APPLICATION = TARGET_LOCALIZATION
