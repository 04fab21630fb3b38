"""Seeds as an axis of the report: runs that differ only by seed are one cell (mean, 95% interval, n), models that the
seeds cannot tell from the best are marked, Table 3 needs a change larger than the seeds' spread, the figures draw
the spread, and a one-seed report bootstraps over its tosses."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import pytest
from matplotlib.container import ErrorbarContainer

from contactbench.evaluation import figures
from contactbench.evaluation.collect import collect
from contactbench.evaluation.report import write_report
from contactbench.evaluation.tables import grid_markdown, importance_sentence

# Test position error per (model, friction) and seed 0, 1, 2; rotation error is 0.1 more, val position error 0.01 more.
# sysid's mean moves by 0.053 from friction 0 to 1, more than 25% of its smallest mean (0.050), less than its seeds'
# widest range (0.100); mujoco_default's moves by 0.130 with seeds 0.020 apart.
POSITIONS = {
    ("mujoco_default", 0.0): [0.20, 0.21, 0.22],
    ("mujoco_default", 1.0): [0.33, 0.34, 0.35],
    ("sysid", 0.0): [0.15, 0.20, 0.25],
    ("sysid", 1.0): [0.30, 0.26, 0.20],
}


def write_runs(root: Path, seeds: list[int], record_seed: bool = True) -> Path:
    """A sweep's metrics.json and per_trajectory.csv, as train.py writes them, for every model, friction and seed."""
    for (model, friction), positions in POSITIONS.items():
        for seed in seeds:
            for split, offset in (("val", 0.01), ("test", 0.0)):
                pos = positions[seed] + offset
                folder = root / f"model={model},seed={seed},variant=frictioncubes_{friction:g}" / split
                folder.mkdir(parents=True)
                summary = {
                    "model": model,
                    "dataset": "frictioncubes",
                    "variant": f"friction={friction:g}",
                    "split": split,
                    "n_trajectories": 4,
                    "context_frames": 6,
                    "noise_mm": 0.0,
                    "frame_stride": 1,
                    "scored_against": "recording",
                    "variant_values": {"friction": friction},
                    "pos_err": pos,
                    "rot_err_rad": pos + 0.1,
                    "floor_penetration_m": 2e-4,
                    "interbody_penetration_m": 0.0,
                    "pairwise_collisions": 0.0,
                    "per_frame": {
                        "frame": [0, 1, 2],
                        "pos_err": [0.0, pos, 2 * pos],
                        "rot_err_rad": [0.0, pos + 0.1, None],
                        "min_vertex_height_m": [0.05, 0.001, 0.0],
                    },
                    **({"seed": seed} if record_seed else {}),
                }
                (folder / "metrics.json").write_text(json.dumps(summary))
                with open(folder / "per_trajectory.csv", "w", newline="") as handle:
                    writer = csv.writer(handle)
                    writer.writerow(["trajectory", "pos_err", "rot_err_rad", "floor_penetration_m"])
                    for toss, scale in enumerate((0.5, 0.9, 1.1, 1.5)):
                        writer.writerow([toss, pos * scale, (pos + 0.1) * scale, 2e-4 * scale])
    return root


def section(text: str, title: str) -> str:
    """A report section's text, from its heading to the next."""
    return re.search(rf"^## {re.escape(title)}.*?\n(.*?)(?=^## )", text, re.S | re.M).group(1)


def test_the_grid_shows_mean_and_interval_over_seeds_and_marks_what_the_seeds_cannot_separate(tmp_path):
    grid = grid_markdown(collect(write_runs(tmp_path, [0, 1, 2])))
    # sysid's seeds (0.15, 0.20, 0.25) spread wider than its tosses: Student t over the seeds' means, 0.200 +- 4.303 x
    # 0.05 / sqrt(3), marked; mujoco_default's seeds are 0.01 apart, so its tosses' bootstrap is the wider interval
    assert (
        "| frictioncubes | friction=0 | – | 0.210 [0.137–0.283] / 0.310 [0.202–0.419] (val 0.220, n=3) † "
        "| **0.200 [0.076–0.324]ˢ / 0.300 [0.176–0.424]ˢ (val 0.210, n=3)** "
        "| pos: mujoco_default ≈ sysid; rot: mujoco_default ≈ sysid |"
    ) in grid
    # friction=1: sysid is better on every toss, but three seeds 0.05 apart cannot tell 0.340 from 0.253
    assert (
        "| frictioncubes | friction=1 | – | 0.340 [0.221–0.459] / 0.440 [0.286–0.594] (val 0.350, n=3) † "
        "| **0.253 [0.128–0.378]ˢ / 0.353 [0.228–0.478]ˢ (val 0.263, n=3)** "
        "| pos: mujoco_default ≈ sysid; rot: mujoco_default ≈ sysid |"
    ) in grid
    assert "† marks a model whose difference from it is not significant" in grid


def test_table3_says_yes_only_for_a_change_larger_than_the_seeds_spread(tmp_path):
    one = figures.importance_table(figures.load_test_runs(write_runs(tmp_path / "one", [0])))
    assert one == {"mujoco_default": {"friction": "Yes"}, "sysid": {"friction": "Yes"}}  # sysid: 0.15 -> 0.30
    three = figures.importance_table(figures.load_test_runs(write_runs(tmp_path / "three", [0, 1, 2])))
    # sysid's means move by more than the 25% threshold, but by less than its seeds' range: not a change it shows
    assert three == {"mujoco_default": {"friction": "Yes"}, "sysid": {"friction": "No"}}
    text = write_report(tmp_path / "three", renders=False).read_text()
    assert importance_sentence(seeded=True) in text and "widest range (min–max) over seeds" in text
    assert "| sysid | No |" in text


def test_the_figures_draw_the_seeds_spread_and_one_seed_as_before(tmp_path, monkeypatch):
    drawn = []
    monkeypatch.setattr(figures, "save_figure", lambda figure, path: drawn.append(figure) or path)
    three = figures.load_test_runs(write_runs(tmp_path / "three", [0, 1, 2]))
    figures.sweep_figure(three, "frictioncubes", tmp_path / "sweep.png")
    position = drawn[-1].axes[0]
    bars = [container for container in position.containers if isinstance(container, ErrorbarContainer)]
    assert len(bars) == 2  # one per model
    sysid_line, sysid_bars = next(line for line in position.lines if line.get_label() == "sysid"), bars[1]
    assert sysid_line.get_ydata() == pytest.approx([0.20, 0.76 / 3])  # the means over seeds
    spans = [segment[:, 1] for segment in sysid_bars.lines[2][0].get_segments()]
    assert [list(span) for span in spans] == [pytest.approx([0.15, 0.25]), pytest.approx([0.20, 0.30])]
    figures.error_over_time_figure(three, "frictioncubes", tmp_path / "time.png")
    assert len(drawn[-1].axes[0].collections) == 2  # a min-max band per model

    one = figures.load_test_runs(write_runs(tmp_path / "one", [0]))
    figures.sweep_figure(one, "frictioncubes", tmp_path / "sweep.png")
    position = drawn[-1].axes[0]
    assert not [container for container in position.containers if isinstance(container, ErrorbarContainer)]
    assert next(line for line in position.lines if line.get_label() == "sysid").get_ydata() == pytest.approx(
        [0.15, 0.30]
    )
    assert len(position.collections) == 2  # the toss bands only
    figures.error_over_time_figure(one, "frictioncubes", tmp_path / "time.png")
    assert not drawn[-1].axes[0].collections


@pytest.mark.parametrize("record_seed", [True, False], ids=["seed recorded", "older metrics.json without a seed"])
def test_a_one_seed_report_bootstraps_over_tosses(tmp_path, record_seed):
    text = write_report(write_runs(tmp_path, [0], record_seed), renders=False).read_text()
    # sysid is below mujoco_default on every toss, so their paired difference never covers 0, though their own
    # intervals overlap
    assert section(text, "Test position error").startswith(
        "\n| dataset | variant | budget | mujoco_default | sysid | not significant (95%) |\n"
        "|---|---|---|---|---|---|\n"
        "| frictioncubes | friction=0 | – | 0.200 [0.130–0.270] / 0.300 [0.195–0.405] (val 0.210) "
        "| **0.150 [0.098–0.202] / 0.250 [0.163–0.338] (val 0.160)** | none |\n"
        "| frictioncubes | friction=1 | – | 0.330 [0.215–0.446] / 0.430 [0.280–0.581] (val 0.340) "
        "| **0.300 [0.195–0.405] / 0.400 [0.260–0.540] (val 0.310)** | none |\n"
    )
    assert section(text, "Table 3, recomputed").startswith(
        "\n'Yes' when a method's mean test position error changes by more than 25% of its smallest value across the "
        "dimension's variants; 'N/A' with fewer than two variants.\n\n"
        "| method | friction |\n|---|---|\n| mujoco_default | Yes |\n| sysid | Yes |\n"
    )
    seed = "0" if record_seed else "–"
    assert f"| sysid | frictioncubes | friction=1 | test | {seed} | 4 | 0.3000 [0.1950–0.4050] |" in text


def test_every_run_keeps_a_row_per_run_with_its_seed(tmp_path):
    root = write_runs(tmp_path, [0, 1, 2])
    text = write_report(root, renders=False).read_text()
    runs = section(text + "## end", "Every run")
    assert "| model | dataset | variant | split | seed | tosses |" in runs
    rows = re.findall(
        r"^\| (mujoco_default|sysid) \| frictioncubes \| friction=[01] \| (val|test) \| ([0-9]) \|", runs, re.M
    )
    assert len(rows) == 2 * 2 * 2 * 3 and {seed for *_, seed in rows} == {"0", "1", "2"}
    # the best in bold reaches the HTML page as bold, not as asterisks
    page = (root / "results.html").read_text()
    assert "<td><b>0.200 [0.076–0.324]ˢ" in page and "**" not in page
    for name in ("frictioncubes.png", "error_over_time_frictioncubes.png", "fig7c_lowest_vertex.png"):
        assert (root / "figures" / name).stat().st_size > 10_000
