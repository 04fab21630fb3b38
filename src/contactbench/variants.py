"""Which generated variants the benchmark names (conf/variant/: the paper's and its future work's). Any other value
(friction=0.3) is a custom variant: it runs, and its results say "not a paper variant" wherever they appear."""

from __future__ import annotations

import functools

from contactbench.config import CONFIG_DIR, format_value

NOT_PAPER = "not a paper variant"


@functools.cache
def _named() -> frozenset[str]:
    return frozenset(path.stem for path in (CONFIG_DIR / "variant").glob("*.yaml"))


def _shortest(value: str) -> str:
    """0.0, 0 and 0.00 are one variant, as cb.fmt names them."""
    try:
        return format_value(float(value))
    except ValueError:
        return value


def paper_variant(dataset: str, variant: str) -> bool | None:
    """Whether conf/variant/ names this variant of a generated dataset (`friction=0.25` of frictioncubes:
    frictioncubes_0.25.yaml; `ground=ramp,faces=6` of terrain: terrain_ramp_6.yaml). None for a dataset with no
    variant files of that form: a recorded one, a user's own folder."""
    if not any(name.startswith(f"{dataset}_") for name in _named()):
        return None
    value = "_".join(_shortest(part.split("=", 1)[-1]) for part in str(variant).split(","))
    return f"{dataset}_{value}" in _named()


def label(dataset: str, variant: str) -> str:
    """The variant as tables and log lines show it: marked when it is not one the benchmark names."""
    return f"{variant} ({NOT_PAPER})" if paper_variant(dataset, variant) is False else str(variant)
