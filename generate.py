"""Generate benchmark datasets with PyBullet: python generate.py dataset=multicubes bodies=3."""

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from contactbench.cli import check_command_line, guarded


@hydra.main(version_base="1.3", config_path="conf", config_name="generate")
@guarded
def main(cfg: DictConfig) -> None:
    from contactbench import checks, folders, runs  # here, not above: --help answers without importing torch

    if runs.crossed_variant(cfg):
        return
    checks.check(cfg)
    folders.claim(cfg, Path(HydraConfig.get().runtime.output_dir), "generate")  # its log folder, not the dataset's
    runs.generate(cfg)


if __name__ == "__main__":
    check_command_line("generate")
    main()
