"""The paper's findings judged from a results file (evaluation/claims.py): a small synthetic results/<budget>.csv in
which every finding holds, then changed cell by cell so that each verdict turns."""

from __future__ import annotations

import csv
import re
import tempfile
from pathlib import Path

import pytest

from contactbench.evaluation import claims
from contactbench.evaluation.results_file import HEADER

FINDINGS = [finding for finding, _, _ in claims.FINDINGS]


def sweep_values(dataset: str) -> list[tuple[float, str]]:
    return claims.sweep(dataset)


def paper_world() -> dict[tuple[str, str, str], dict[str, tuple[float, float]]]:
    """(model, dataset, variant) -> {metric: (mean, half-width of its interval)}: a world where every finding of
    the paper holds."""
    cells: dict = {}

    def put(model, dataset, metric, means, half=0.005):
        for (_, variant), mean in zip(sweep_values(dataset), means):
            cells.setdefault((model, dataset, variant), {})[metric] = (mean, half)

    rising = [0.10, 0.15, 0.20, 0.25, 0.30]
    for model in ("sysid", "hybrid"):  # Fig. 1: analytical models' position error rises, rotation too
        put(model, "bouncycubes", "pos_err", rising)
        put(model, "bouncycubes", "rot_err_rad", rising)
    put("gnn", "bouncycubes", "pos_err", [0.20, 0.21, 0.20, 0.22, 0.21])  # flat
    put("gnn", "bouncycubes", "rot_err_rad", rising)
    for model in ("sysid", "gnn"):  # Fig. 2: mu = 0 lowest, by less than Table 3's threshold (friction: No)
        put(model, "frictioncubes", "pos_err", [0.17, 0.20, 0.21, 0.20, 0.21])
        put(model, "frictioncubes", "rot_err_rad", [0.17, 0.20, 0.21, 0.20, 0.21])
    put("hybrid", "frictioncubes", "pos_err", [0.05, 0.20, 0.21, 0.20, 0.21])  # Table 3: friction Yes
    put("hybrid", "frictioncubes", "rot_err_rad", [0.05, 0.20, 0.21, 0.20, 0.21])
    for model in ("sysid", "gnn"):
        put(model, "polyhedra", "pos_err", [0.2] * 7)
        put(model, "polyhedra", "rot_err_rad", [0.10, 0.20, 0.30, 0.40, 0.41, 0.40, 0.42])  # Fig. 3: grows, plateaus
        put(model, "multicubes", "pos_err", [0.10, 0.12, 0.14, 0.16, 0.18])  # Fig. 5: both errors grow
        put(model, "multicubes", "rot_err_rad", [0.10, 0.12, 0.14, 0.16, 0.18])
        put(model, "multicubes", "floor_penetration_m", [0.001] * 5, 0.0001)
    put("gnn", "multicubes", "interbody_penetration_m", [0.0, 0.004, 0.005, 0.006, 0.007], 0.0005)  # Fig. 7a
    put("sysid", "multicubes", "interbody_penetration_m", [0.0, 0.001, 0.001, 0.001, 0.001], 0.0002)
    for (_, dataset, variant), metrics in cells.items():
        if dataset == "multicubes":  # Fig. 7b: at most K pairs (the recordings' count, the same for every model)
            metrics["pairs"] = (float(variant.split("=")[1]) - 1, 0.0)
    return cells


def write(path, cells, extra_rows=()):
    """The cells as results_file writes them: test split, plain observation, one seed."""
    rows = []
    for (model, dataset, variant), metrics in cells.items():
        row = dict.fromkeys(HEADER, "")
        row.update(model=model, dataset=dataset, variant=variant, split="test", budget="quick", noise_mm="0")
        row.update(frame_stride="1", seeds="0", tosses="40", commit="unknown", date="unknown", wall_s="unknown")
        for metric, (mean, half) in metrics.items():
            if metric == "pairs":
                row["pairwise_collisions_true_max"] = f"{mean:g}"
                continue
            row.update({metric: f"{mean:.6g}", f"{metric}_low": f"{mean - half:.6g}"})
            row.update({f"{metric}_high": f"{mean + half:.6g}", f"{metric}_interval": "tosses"})
        rows.append(row)
    rows += list(extra_rows)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=HEADER, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return path


def verdicts(path) -> dict[str, str]:
    return {claim.finding: claim.verdict for claim in claims.check(claims.Results.read(path))}


def test_every_finding_is_reproduced_where_the_results_say_what_the_paper_says(tmp_path):
    got = verdicts(write(tmp_path / "quick.csv", paper_world()))
    assert got == dict.fromkeys(FINDINGS, claims.REPRODUCED)


def set_metric(cells, model, dataset, metric, means, half=0.005):
    for (_, variant), mean in zip(sweep_values(dataset), means):
        cells[(model, dataset, variant)][metric] = (mean, half)


def turned(change) -> dict[str, str]:
    """Verdicts of the paper's world after one change (a function of the cells)."""
    cells = paper_world()
    change(cells)
    with tempfile.TemporaryDirectory() as folder:
        return verdicts(write(Path(folder) / "quick.csv", cells))


@pytest.mark.parametrize(
    "finding, change, verdict",
    [
        (  # the analytical models' position error falls with restitution
            "Fig. 1 (restitution)",
            lambda c: [
                set_metric(c, m, "bouncycubes", "pos_err", [0.30, 0.25, 0.20, 0.15, 0.10]) for m in ("sysid", "hybrid")
            ],
            claims.REVERSED,
        ),
        (  # the GNN's rises as well
            "Fig. 1 (restitution)",
            lambda c: set_metric(c, "gnn", "bouncycubes", "pos_err", [0.10, 0.15, 0.20, 0.25, 0.30]),
            claims.NOT_REPRODUCED,
        ),
        (  # a rise inside intervals that all overlap is no rise
            "Fig. 1 (restitution)",
            lambda c: set_metric(c, "sysid", "bouncycubes", "pos_err", [0.10, 0.15, 0.20, 0.25, 0.30], 0.2),
            claims.NOT_REPRODUCED,
        ),
        (  # mu = 0 the hardest for every model
            "Fig. 2 (friction)",
            lambda c: [
                set_metric(c, m, "frictioncubes", "pos_err", [0.40, 0.20, 0.21, 0.20, 0.21])
                for m in ("sysid", "gnn", "hybrid")
            ],
            claims.REVERSED,
        ),
        (  # a trend over mu > 0 for one model
            "Fig. 2 (friction)",
            lambda c: set_metric(c, "gnn", "frictioncubes", "pos_err", [0.05, 0.10, 0.20, 0.30, 0.40]),
            claims.NOT_REPRODUCED,
        ),
        (  # rotation error keeps growing with the faces, no plateau
            "Fig. 3 (faces)",
            lambda c: set_metric(c, "gnn", "polyhedra", "rot_err_rad", [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7]),
            claims.NOT_REPRODUCED,
        ),
        (  # both errors fall with the number of bodies
            "Fig. 5 (bodies)",
            lambda c: [
                set_metric(c, m, "multicubes", k, [0.18, 0.16, 0.14, 0.12, 0.10])
                for m in ("sysid", "gnn")
                for k in ("pos_err", "rot_err_rad")
            ],
            claims.REVERSED,
        ),
        (  # SysID's bodies interpenetrate more than the GNN's
            "Fig. 7a (inter-body penetration)",
            lambda c: set_metric(
                c, "sysid", "multicubes", "interbody_penetration_m", [0, 0.01, 0.01, 0.01, 0.01], 0.001
            ),
            claims.REVERSED,
        ),
        (  # a recorded toss of four cubes touched six pairs
            "Fig. 7b (pairwise collisions)",
            lambda c: c[("gnn", "multicubes", "bodies=4")].update(pairs=(6.0, 0.0)),
            claims.NOT_REPRODUCED,
        ),
        (  # friction matters to SysID-MuJoCo (its position error moves by far more than the threshold)
            "Table 3",
            lambda c: set_metric(c, "sysid", "frictioncubes", "pos_err", [0.05, 0.20, 0.21, 0.20, 0.21]),
            claims.NOT_REPRODUCED,
        ),
    ],
)
def test_a_verdict_turns_with_the_cells_it_is_judged_from(finding, change, verdict):
    got = turned(change)
    assert got[finding] == verdict
    # the others are judged from other cells (Table 3 from every sweep's, so it may turn too)
    others = [key for key in FINDINGS if key not in (finding, "Table 3")]
    assert [got[key] for key in others] == [claims.REPRODUCED] * len(others)


def test_a_missing_cell_makes_not_run_and_says_which(tmp_path):
    cells = paper_world()
    del cells[("hybrid", "bouncycubes", "restitution=0.75")]
    # a val row, or a noisy observation, of the missing cell does not stand in for the plain test cell
    stand_ins = []
    for split, noise in (("val", "0"), ("test", "1")):
        row = dict.fromkeys(HEADER, "")
        row.update(model="hybrid", dataset="bouncycubes", variant="restitution=0.75", split=split, noise_mm=noise)
        row.update(frame_stride="1", pos_err="0.2", rot_err_rad="0.2")
        stand_ins.append(row)
    path = write(tmp_path / "quick.csv", cells, stand_ins)
    by_finding = {claim.finding: claim for claim in claims.check(claims.Results.read(path))}
    for finding in ("Fig. 1 (restitution)", "Table 3"):
        assert by_finding[finding].verdict == claims.NOT_RUN
        assert "hybrid bouncycubes pos_err at restitution=0.75" in by_finding[finding].ours
    assert by_finding["Fig. 2 (friction)"].verdict == claims.REPRODUCED
    # an empty file judges nothing, and says what every finding needs
    empty = write(tmp_path / "empty.csv", {})
    assert verdicts(empty) == dict.fromkeys(FINDINGS, claims.NOT_RUN)


def test_the_table_is_written_beside_its_results_file(tmp_path):
    path, text = claims.write_claims(write(tmp_path / "quick.csv", paper_world()))
    assert path == tmp_path / "quick_claims.md" and path.read_text() == text
    rows = [line for line in text.splitlines() if line.startswith("| Fig.") or line.startswith("| Table 3")]
    assert len(rows) == len(FINDINGS) and all(line.endswith("| **reproduced** |") for line in rows)
    assert "`quick.csv`" in text  # named by its file, not by a path of this machine
    # every figure printed with an interval holds its mean inside it
    for mean, low, high in re.findall(r"([0-9.]+) \[([0-9.]+)–([0-9.]+)\]", text):
        assert float(low) <= float(mean) <= float(high)
