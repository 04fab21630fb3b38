"""Score a model on a split and write metrics.json: python evaluate.py model=mujoco_default dataset=contactnets_cube."""

from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from contactbench.cli import check_command_line, guarded


@hydra.main(version_base="1.3", config_path="conf", config_name="evaluate")
@guarded
def main(cfg: DictConfig) -> dict:
    from contactbench import runs  # here, not above: --help answers without importing torch and the engines

    return runs.evaluate(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    check_command_line("evaluate")
    main()
