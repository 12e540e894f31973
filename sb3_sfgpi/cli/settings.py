"""``train --set KEY=VALUE``: a run's method settings, the domain's preset with the user's overrides, checked.

The presets hold the settings that won their measurements (docs: the levers page); ``--set`` changes one for a run
without a command-line option of its own for each.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.cli.presets import SETTABLE, DomainPreset
from sb3_sfgpi.cli.values import key_values

#: Settings that do not change a run's results: a resumed run may use other values.
MACHINE_SETTINGS = ("eval_workers",)


def method_settings(preset: DomainPreset, items: Sequence[str], algo: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """
    The method settings of a run: the preset's, with the ``--set`` items over them.

    :param items: the ``KEY=VALUE`` strings of ``--set``
    :param algo: ``ma-sfols``, ``random`` or ``fixed`` (some settings apply to some algorithms only)
    :return: every setting of :data:`SETTABLE`, and the ones given
    :raises UsageError: an unknown key, a value of the wrong kind, or a setting its algorithm has no use for
    """
    given = key_values(items, "--set")
    for key, value in given.items():
        if key not in SETTABLE:
            raise UsageError(f"--set {key}: unknown setting (known: {', '.join(SETTABLE)})")
        check, what = SETTABLE[key]
        if not check(value):
            raise UsageError(f"--set {key} must be {what}, got {value!r}")
    settings = {key: given.get(key, preset.setting(key)) for key in SETTABLE}
    if algo != "ma-sfols":
        if "ols_batch" in given:
            raise UsageError(f"--set ols_batch is only for --algo ma-sfols (OLS weights), not --algo {algo}")
        settings["ols_batch"] = "top"
    if algo == "fixed":
        if "validation_weights" in given:
            raise UsageError("--set validation_weights is not for --algo fixed: every policy of a fixed run is kept")
        settings["validation_weights"] = 0
    for rule in ("prune", "admit_together"):
        if given.get(rule) and not settings["validation_weights"]:
            raise UsageError(f"--set {rule}=true needs validation weights (--set validation_weights=N, N > 0)")
        settings[rule] = settings[rule] and settings["validation_weights"] > 0
    return settings, given


def check_resumed(given: dict[str, Any], stored: dict[str, Any]) -> None:
    """
    Refuse ``--set`` values that would change a resumed run.

    :param given: the settings given with ``--set``
    :param stored: the run's ``run.json``
    :raises UsageError: a setting that differs from the stored one
    """
    for key, value in given.items():
        before = stored.get(key)
        if key not in MACHINE_SETTINGS and value != before:
            raise UsageError(f"--resume: --set {key}={value} would change the run's {key} ({before})")
