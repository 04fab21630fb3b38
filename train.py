"""Fit a contact model on a dataset's train split, select on val: python train.py model=gnn dataset=multicubes
bodies=3."""

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from contactbench.cli import check_command_line, guarded


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
@guarded
def main(cfg: DictConfig) -> float:
    from contactbench import runs  # here, not above: --help answers without importing torch and the engines

    return runs.train(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    check_command_line("train")
    main()
