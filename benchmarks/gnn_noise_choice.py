"""Could the GNN choose its noise on val sooner? What deciding early would have chosen, read from finished fits.

A `gnn` fit at quick trains every setting of its `choose_on_val` grid (conf/model/gnn.yaml: three noise levels) to
max_steps and keeps the one whose best checkpoint scores lowest on val: three fits' cost. Deciding at step D instead
(every setting to D, then only the leader on to max_steps) costs settings x D + (max_steps - D) steps, and where the
leader at D is the final winner the kept model is the very same one: a setting's fit resumes exactly where it
stopped. This reads the val curves every finished fit logged (csv/metrics.csv, `<setting>/val/pos_err` at each
validation) and prints, per fit and per decision step D: the leader by best val so far, whether it is the winner, and
the regret, the leader's own final best val over the winner's, minus 1 (val only: only the winner was scored on test).

    python benchmarks/gnn_noise_choice.py outputs/matrix/quick        # every gnn fit with a choice below the folder
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path


def val_curves(run: Path) -> dict[str, list[tuple[int, float]]]:
    """Each setting's (step, val/pos_err) at every validation of the fit, in order."""
    curves: dict[str, list[tuple[int, float]]] = {}
    for metrics in sorted(run.glob("csv/**/metrics.csv")):
        with open(metrics, newline="") as handle:
            for row in csv.DictReader(handle):
                for column, value in row.items():
                    if column and column.endswith("/val/pos_err") and value:
                        curves.setdefault(column.removesuffix("/val/pos_err"), []).append(
                            (int(row["step"]), float(value))
                        )
    return {name: sorted(set(points)) for name, points in curves.items()}


def best_until(curve: list[tuple[int, float]], step: int) -> float:
    return min((value for at, value in curve if at <= step), default=math.inf)


def fits(root: Path):
    """(run folder, its val curves, the winner's setting name) of every finished fit that chose among settings."""
    for fitted in sorted(root.glob("**/fitted.json")):
        record = json.loads(fitted.read_text())
        if record.get("model") != "gnn" or "candidates" not in record:
            continue
        curves = val_curves(fitted.parent)
        winner = record["checkpoint"].split("/")[0]
        if len(curves) == len(record["candidates"]) and winner in curves:
            yield fitted.parent, curves, winner


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("roots", nargs="+", type=Path)
    args = parser.parse_args()
    found = [fit for root in args.roots for fit in fits(root)]
    if not found:
        raise SystemExit(f"no finished gnn fit with settings chosen on val below {', '.join(map(str, args.roots))}")
    steps = sorted({at for _, curves, _ in found for curve in curves.values() for at, _ in curve})
    final = steps[-1]
    summary = {step: [] for step in steps}
    print(f"{'fit':60s} {'winner':18s} " + " ".join(f"D={step + 1:<6d}" for step in steps))
    for run, curves, winner in found:
        winner_best = best_until(curves[winner], final)
        cells = []
        for step in steps:
            leader = min(curves, key=lambda name: best_until(curves[name], step))
            regret = best_until(curves[leader], final) / winner_best - 1
            summary[step].append(regret)
            cells.append("same   " if leader == winner else f"{regret:+.1%}".ljust(7))
        print(f"{str(run.relative_to(run.parents[1]))[-60:]:60s} {winner:18s} " + " ".join(cells))
    settings = len(found[0][1])
    print(f"\n{len(found)} fits, {settings} settings, {final + 1} steps each")
    for step in steps:
        regrets = summary[step]
        cost = (settings * (step + 1) + (final - step)) / (settings * (final + 1))
        same, mean = sum(regret == 0 for regret in regrets), sum(regrets) / len(regrets)
        print(
            f"decide at {step + 1:5d}: the winner {same}/{len(regrets)}, regret mean {mean:+.2%} max "
            f"{max(regrets):+.2%}; steps {cost:.2f} of choosing at the end"
        )


if __name__ == "__main__":
    main()
