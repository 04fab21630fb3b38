"""contactbench: benchmark rigid-body contact models on recorded and generated tosses."""

from contactbench import config as _config  # noqa: F401  (registers the OmegaConf resolvers the configs use)
