"""Generate benchmark datasets with PyBullet: python generate.py dataset=multicubes bodies=3."""
import hydra
from omegaconf import DictConfig

from contactbench import runs
from contactbench.cli import guarded


@hydra.main(version_base="1.3", config_path="conf", config_name="generate")
@guarded
def main(cfg: DictConfig) -> None:
    runs.generate(cfg)


if __name__ == "__main__":
    main()
