"""Locate, name, model and prove the physics a simulator misses: python diagnose.py recordings=PATH."""

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from contactbench.cli import check_command_line, guarded


@hydra.main(version_base="1.3", config_path="conf", config_name="diagnose")
@guarded
def main(cfg: DictConfig) -> str:
    from contactbench import runs  # here, not above: --help answers without importing torch and the engines

    return runs.diagnose(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    check_command_line("diagnose")
    main()
