"""What `--help` lists, read from the config groups and the code when the help is printed: a model, budget or dataset
added to conf/ or an effect added to the library is in the help without anyone editing it (conf/hydra/help/).

Only YAML and the effect names are read here: the help must not wait for torch, Lightning or an engine to import."""

from __future__ import annotations

from omegaconf import OmegaConf

from contactbench.config import CONFIG_DIR

WORDS = "zero one two three four five six seven eight nine ten eleven twelve".split()
WIDTH, INDENT = 100, 6  # a list's lines in the help: after its `key=`, within 120 columns; continued further in


def number_word(number: int) -> str:
    """A count as prose writes it: words up to twelve, digits above."""
    return WORDS[number] if 0 <= number < len(WORDS) else str(number)


def listing(items: list[str]) -> str:
    """`a|b|c`, broken after a `|` where a line would pass WIDTH."""
    lines, line = [], ""
    for item in items:
        if line and len(line) + 1 + len(item) > WIDTH:
            lines.append(line + "|")
            line = item
        else:
            line = f"{line}|{item}" if line else item
    return ("\n" + " " * INDENT).join([*lines, line])


def options(group: str) -> str:
    """A config group's options, as `a|b|c`."""
    return listing(sorted(path.stem for path in (CONFIG_DIR / group).glob("*.yaml")))


def dataset_settings() -> dict[str, list[str]]:
    """Each dataset's own top-level settings, those that pick its variant ({"terrain": ["ground", "faces"], ...})."""
    found = {}
    for path in sorted((CONFIG_DIR / "dataset").glob("*.yaml")):
        found[path.stem] = [str(key) for key in OmegaConf.load(path) if key not in ("dataset", "defaults")]
    return found


def datasets(generated_only: bool = False) -> str:
    """Every dataset with its settings: `frictioncubes (friction=)|...|recordings (recordings=)`. generated_only: those
    generate.py makes (a scene to generate), not the recorded ones."""
    listed = []
    for name, keys in dataset_settings().items():
        if generated_only and OmegaConf.load(CONFIG_DIR / "dataset" / f"{name}.yaml").dataset.get("scene") is None:
            continue
        listed.append(f"{name} ({', '.join(f'{key}=' for key in keys)})" if keys else name)
    return listing(listed)


def count(group: str) -> int:
    return len(list((CONFIG_DIR / group).glob("*.yaml")))


def effects() -> str:
    """How many effects diagnose.py's library models, in words."""
    from contactbench.sim.effects import EFFECT_NAMES

    return number_word(len(EFFECT_NAMES))


def register_resolvers() -> None:
    OmegaConf.register_new_resolver("cb.options", options, replace=True)
    OmegaConf.register_new_resolver("cb.datasets", datasets, replace=True)
    OmegaConf.register_new_resolver("cb.count", count, replace=True)
    OmegaConf.register_new_resolver("cb.effects", effects, replace=True)


register_resolvers()
