"""The one place where configuration becomes objects.

``instantiate`` is Hydra's, restricted to classes and functions of demon_lab, torch and
Lightning: a config can name only those as ``_target_``, so a config file never runs
arbitrary code.
"""

from __future__ import annotations

from typing import Any

from demon_lab.resources import DATA, cache_root

ALLOWED_TARGETS = ("demon_lab.", "torch.", "lightning.")


def _times(value: Any, factor: Any) -> int:
    """``${times:${scale.steps.dm1},4}``: a step count scaled by an integer factor."""
    if isinstance(value, bool) or isinstance(factor, bool) or not isinstance(value, int) or not isinstance(factor, int):
        raise ConfigError(f"times: expected two integers, got {value!r} and {factor!r}")
    return value * factor


FOLDER_NAME_MAX = 200
"""The longest job folder name (bytes): most file systems refuse a name over 255."""


def _folder(name: Any) -> str:
    """``${folder:${hydra.job.override_dirname}}``: the job folder's name, the overrides themselves
    while they fit in :data:`FOLDER_NAME_MAX` bytes; a longer one is cut at an override's end and
    ends in a digest of the whole (the same command, the same folder: a re-issued job resumes)."""
    import hashlib

    name = str(name)
    if len(name.encode()) <= FOLDER_NAME_MAX:
        return name
    kept = ""
    for part in name.split(","):
        if len((kept + "," + part).encode()) > FOLDER_NAME_MAX - 20:
            break
        kept = f"{kept},{part}" if kept else part
    return f"{kept},+{hashlib.sha256(name.encode()).hexdigest()[:12]}"


def register_resolvers() -> None:
    """``${bundled:NAME}`` -> the absolute path of a real sample that ships inside the package
    (:data:`demon_lab.resources.DATA`), whatever the working directory; ``${times:N,K}`` -> N x K
    for integers (nothing else is evaluated); ``${non_semantic_overrides:}`` -> the job's
    overrides that change no result; ``${folder:NAME}`` -> a job folder's name that fits the file
    system (:func:`_folder`); ``${demon_lab_cache:}`` -> :func:`demon_lab.resources.cache_root`."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("bundled"):
        OmegaConf.register_new_resolver("bundled", lambda name="": str(DATA / name))
    if not OmegaConf.has_resolver("times"):
        OmegaConf.register_new_resolver("times", _times)
    if not OmegaConf.has_resolver("folder"):
        OmegaConf.register_new_resolver("folder", _folder)
    if not OmegaConf.has_resolver("non_semantic_overrides"):
        OmegaConf.register_new_resolver("non_semantic_overrides", _non_semantic_overrides)
    if not OmegaConf.has_resolver("demon_lab_cache"):
        OmegaConf.register_new_resolver("demon_lab_cache", lambda: str(cache_root()))


def _non_semantic_overrides(*, _root_: Any) -> list[str]:
    """The keys (or groups) of the job's overrides that do not change what it computes
    (:func:`demon_lab.pipeline.identity.is_semantic`): Hydra's ``override_dirname`` leaves them out."""
    from demon_lab.pipeline.identity import is_semantic

    keys = [line.split("=", 1)[0].lstrip("+~") for line in _root_.hydra.overrides.task]
    return [key for key in keys if not is_semantic(key)]


class ConfigError(ValueError):
    """A bad configuration value: the message names the key and what is allowed (one line)."""


def expect_int(key: str, value: Any, minimum: int | None = None) -> int:
    """``value`` if it is an integer (>= ``minimum``), else the ConfigError line naming ``key``."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{key}: expected an integer{'' if minimum is None else f' >= {minimum}'}, got {value!r}")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{key}: expected an integer >= {minimum}, got {value}")
    return value


def expect_flag(key: str, value: Any) -> bool:
    """``value`` if it is true or false, else the ConfigError line naming ``key``."""
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: expected true or false, got {value!r}")
    return value


def expect_positive(key: str, value: Any, allow_zero: bool = False) -> float:
    """``value`` as a float if it is a positive (or, with ``allow_zero``, non-negative) number."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not (value >= 0 if allow_zero else value > 0):
        raise ConfigError(f"{key}: expected a {'non-negative' if allow_zero else 'positive'} number, got {value!r}")
    return float(value)


def expect_choice(key: str, value: Any, allowed: tuple) -> None:
    """Nothing if ``value`` is one of ``allowed``, else the ConfigError line listing them."""
    if value not in allowed:
        shown = ", ".join("null" if a is None else str(a) for a in allowed)
        raise ConfigError(f"{key}: expected one of {shown}, got {value!r}")


def expect_fraction(key: str, value: Any, low_open: bool = False, note: str = "") -> float:
    """``value`` if it is a number in [0, 1] (``low_open``: (0, 1]), else the ConfigError line."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
            0 < value <= 1 if low_open else 0 <= value <= 1):
        raise ConfigError(f"{key}: expected a fraction of the stage in {'(0, 1]' if low_open else '[0, 1]'}{note}, "
                          f"got {value!r}")
    return float(value)


def drop_missing_sources(cfg: Any, train: bool = True) -> list[str]:
    """Remove the data sources marked ``optional: true`` whose ``path`` does not exist, and the
    ``optional`` marks (DeMoN's files under ``data.root``: whichever are present). The training
    sources only with ``train`` (a job passes its ``train``). Returns one line per split that lost
    sources, naming them; ConfigError when a split loses all of them."""
    from pathlib import Path

    from omegaconf import OmegaConf, open_dict

    notes = []
    splits = [("test", lambda e: e)] + ([("train", lambda e: e.dataset)] if train else [])
    for split, source_of in splits:
        entries = cfg.data.get(split)
        if not entries or not any(source_of(e).get("optional", False) for e in entries):
            continue
        kept, missing = [], []
        for entry in entries:
            source = source_of(entry)
            if source.get("optional", False) and not Path(str(source.path)).exists():
                missing.append(str(source.path))
            else:
                kept.append(entry)
        if not kept:
            folder = str(Path(missing[0]).parent)
            names = ", ".join(Path(m).name for m in missing)
            raise ConfigError(f"data.{split}: none of its files is present in {folder} (looked for {names})")
        with open_dict(cfg):
            cfg.data[split] = OmegaConf.create([OmegaConf.to_container(e, resolve=False) for e in kept])
            for entry in cfg.data[split]:
                source_of(entry).pop("optional", None)
        if missing:
            notes.append(f"data.{split}: not found, skipped: {', '.join(missing)}")
    return notes


def _check_targets(node: Any, path: str = "") -> None:
    from omegaconf import DictConfig, ListConfig

    if isinstance(node, DictConfig):
        target = node.get("_target_") if "_target_" in node else None
        if target is not None and not str(target).startswith(ALLOWED_TARGETS):
            raise ConfigError(f"{path or '<root>'}._target_: {target!r} is not allowed "
                              f"(only {', '.join(p + '*' for p in ALLOWED_TARGETS)})")
        for key in node:
            _check_targets(node._get_node(key), f"{path}.{key}" if path else str(key))
    elif isinstance(node, ListConfig):
        for i, item in enumerate(node._iter_ex(resolve=False)):
            _check_targets(item, f"{path}[{i}]")


def instantiate(cfg: Any, **kwargs: Any) -> Any:
    """``hydra.utils.instantiate`` after checking every ``_target_`` in the tree."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate as hydra_instantiate
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if not isinstance(cfg, DictConfig | ListConfig):
        cfg = OmegaConf.create(cfg)
    if isinstance(cfg, DictConfig) and "optional" in cfg:  # a data source's mark, not an argument
        plain = OmegaConf.to_container(cfg, resolve=True)
        plain.pop("optional")
        cfg = OmegaConf.create(plain)
    _check_targets(cfg)
    try:
        return hydra_instantiate(cfg, **kwargs)
    except InstantiationException as e:
        # Hydra wraps the constructor's error; demon_lab's own errors are already one clear line.
        cause = e.__cause__
        if isinstance(cause, ValueError):
            raise cause from None
        raise ConfigError(str(e).splitlines()[0]) from None


register_resolvers()
