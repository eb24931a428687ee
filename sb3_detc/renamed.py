"""Files saved under the names sb3-detc used before the broadcast decision had one name.

Every agent's decision to broadcast (1) or stay silent (0) is called ``broadcast`` throughout:
the action key, ``info["broadcast"]``, ``broadcast_cost``, MAPPOC's ``broadcast_*``
hyperparameters. Models, policies, run logs and hyperparameter entries saved before used
``comm``, ``comm_cost`` and ``option_*``. This module is the one place that maps the old names
to the new ones; loading a model or a policy, reading a run's ``progress.csv`` and reading a
saved rl-zoo3 configuration go through it, so earlier results stay readable.
"""

from __future__ import annotations

from typing import Any

from gymnasium import spaces

__all__ = [
    "NEGATED",
    "REMOVED",
    "RENAMED",
    "renamed_action_space",
    "renamed_column",
    "renamed_keys",
    "renamed_saved_data",
]

#: Old name -> new name (saved attributes, hyperparameters, environment arguments).
RENAMED: dict[str, str] = {
    "comm_cost": "broadcast_cost",
    "option_ent_coef": "broadcast_ent_coef",
    "clip_range_option": "clip_range_broadcast",
    "normalize_option_advantage": "normalize_broadcast_advantage",
    "option_advantage": "broadcast_advantage",
    "option_advantage_offset": "broadcast_advantage_offset",
    "train_option_policy": "train_broadcast_policy",
}

#: Old name of a switch -> new name of the opposite switch (the saved value is negated). A policy saved with
#: ``deterministic_options=False`` sampled its options in every evaluation: ``sample_options=True`` now.
NEGATED: dict[str, str] = {"deterministic_options": "sample_options"}

#: Settings that earlier versions saved and that no longer exist: a loaded model drops them.
#: ``overlap_rollouts`` (rollouts sampled during the update) learned worse over 5 seeds on Multiwalker.
REMOVED: tuple[str, ...] = ("overlap_rollouts",)

#: The action key of the broadcast decision before and now.
OLD_ACTION_KEY, ACTION_KEY = "comm", "broadcast"


def renamed_action_space(space: Any) -> Any:
    """A joint action space with the decision under its current key (other spaces unchanged).

    :param space: an action space, possibly ``Dict(comm=..., control=...)``
    :return: the same space with ``comm`` renamed ``broadcast`` (in its place), else ``space`` itself
    """
    if not isinstance(space, spaces.Dict) or OLD_ACTION_KEY not in space.spaces:
        return space
    return spaces.Dict({ACTION_KEY if key == OLD_ACTION_KEY else key: value for key, value in space.spaces.items()})


def renamed_keys(mapping: dict[str, Any]) -> dict[str, Any]:
    """A mapping with old names replaced by new ones (a new name given as well wins).

    :param mapping: e.g. saved model data, policy arguments, hyperparameters or environment arguments
    :return: a new dict; a switch of :data:`NEGATED` under its old name becomes the new switch, negated
    """
    renamed = {key: value for key, value in mapping.items() if key not in RENAMED and key not in NEGATED}
    for old, value in mapping.items():
        if old in RENAMED:
            renamed.setdefault(RENAMED[old], value)
        elif old in NEGATED:
            renamed.setdefault(NEGATED[old], not value)
    return renamed


def renamed_saved_data(
    data: dict[str, Any], custom_objects: dict[str, Any] | None, kwargs: dict[str, Any]
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """What SB3's ``load`` of a model saved under earlier names needs to restore it under the current ones.

    Attributes saved under earlier names become the current ones unless given (as custom objects or
    keyword arguments, also under earlier names); the model drops the old names when it is set up.

    :param data: the saved model's data (``load_from_zip_file``)
    :param custom_objects: the custom objects given to ``load``
    :param kwargs: the attributes given to ``load``
    :return: the custom objects (with the action space under its current key) and the attributes to set
    """
    if "action_space" in data:
        action_space = renamed_action_space(data["action_space"])
        if action_space is not data["action_space"]:
            custom_objects = {"action_space": action_space, **(custom_objects or {})}
    saved = {RENAMED[key]: value for key, value in data.items() if key in RENAMED}
    given = {key: value for key, value in (custom_objects or {}).items() if key in saved}
    return custom_objects, {**saved, **given, **renamed_keys(kwargs)}


def renamed_column(name: str) -> str:
    """A logged value's current name (``train/option_ent_coef`` -> ``train/broadcast_ent_coef``).

    :param name: a column of a ``progress.csv``
    :return: its current name
    """
    group, _, key = name.rpartition("/")
    return f"{group}/{RENAMED.get(key, key)}" if group else RENAMED.get(key, key)
