"""Two versions of one method on the same suite logs, field by field: the ratio new/old of
every metric of every run, its geometric mean over the runs, and the spread of that ratio
between seeds (the noise a change is judged against: the estimator is deterministic, so the
same log gives the same numbers; a different seed gives a different log).

    python benchmarks/compare_suites.py --old OLD/suite.json [...] --new NEW/suite.json [...]
        [--method physics] [--out DIR]

--old and --new take one suite.json per seed, in the same order (each pair: the same logs,
run by the two versions). Prints a table and writes DIR/compare.md and DIR/compare.json.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from estimator.evaluate import TRAJECTORY_KEYS

# the errors compared (lower is better), ANEES (as |log ANEES|) and the wall time
METRICS = (
    *TRAJECTORY_KEYS,
    "contact_force_pct_weight",
    "position_anees",
    "occluded_position_mm",
    "wall_over_duration",
)


def runs(path: Path, method: str) -> dict[tuple[str, str], dict]:
    """(scenario, condition) → metrics of `method`'s runs in one suite.json."""
    suite = json.loads(path.read_text())
    return {
        (r["scenario"], r["condition"]): r["metrics"]
        for r in suite["runs"]
        if r["method"] == method and r.get("metrics")
    }


def ratios(old: dict, new: dict) -> dict[tuple[str, str], dict[str, float]]:
    """new/old per run and metric (runs and metrics both have; ANEES as its distance from 1,
    |log ANEES|, so that a ratio above 1 is worse for every metric)."""
    out = {}
    for key in sorted(old.keys() & new.keys()):
        row = {}
        for metric in METRICS:
            a, b = old[key].get(metric), new[key].get(metric)
            if a is None or b is None or not a > 0 or not b > 0:
                continue
            if metric == "position_anees":
                a, b = abs(math.log(a)), abs(math.log(b))
                if a == 0:
                    continue
            row[metric] = b / a
        out[key] = row
    return out


def cell(value: float, bold: bool = False) -> str:
    if math.isnan(value):
        return "–"
    return f"**{value:.3f}**" if bold else f"{value:.3f}"


def geometric_mean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values)) if values else math.nan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--old", type=Path, nargs="+", required=True)
    parser.add_argument("--new", type=Path, nargs="+", required=True)
    parser.add_argument("--method", default="physics")
    parser.add_argument("--out", type=Path, default=Path("out/compare"))
    args = parser.parse_args()
    if len(args.old) != len(args.new):
        parser.error("--old and --new need one suite.json each per seed, in the same order")
    per_seed = [
        ratios(runs(o, args.method), runs(n, args.method))
        for o, n in zip(args.old, args.new, strict=True)
    ]
    # each seed's geometric mean per metric over its runs; the spread of those between seeds
    by_seed = [
        {m: geometric_mean([r[m] for r in seed.values() if m in r]) for m in METRICS}
        for seed in per_seed
    ]
    summary = {}
    for m in METRICS:
        values = [s[m] for s in by_seed if not math.isnan(s[m])]
        summary[m] = {
            "geomean": geometric_mean(values),
            "seed_min": min(values, default=math.nan),
            "seed_max": max(values, default=math.nan),
        }
    header = "| seed | run | " + " | ".join(METRICS) + " |"
    lines = [header, "|" + "---|" * (len(METRICS) + 2)]
    for i, seed in enumerate(per_seed):
        for (scenario, condition), row in seed.items():
            cells = [cell(row.get(m, math.nan)) for m in METRICS]
            lines.append(f"| {i} | {scenario}/{condition} | " + " | ".join(cells) + " |")
        cells = [cell(by_seed[i][m], bold=True) for m in METRICS]
        lines.append(f"| {i} | geometric mean | " + " | ".join(cells) + " |")
    cells = [
        f"{cell(summary[m]['geomean'], bold=True)} ({cell(summary[m]['seed_min'])}–"
        f"{cell(summary[m]['seed_max'])})"
        for m in METRICS
    ]
    lines.append("| all | geometric mean (seed range) | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "compare.md").write_text(
        f"{args.method}: new/old per run and metric (position_anees: |log ANEES| new/old; "
        "above 1 is worse)\n\n    python benchmarks/compare_suites.py "
        + " ".join(sys.argv[1:])
        + "\n\n"
        + table
        + "\n"
    )
    (args.out / "compare.json").write_text(
        json.dumps(
            {
                "method": args.method,
                "old": [str(p) for p in args.old],
                "new": [str(p) for p in args.new],
                "runs": [{f"{s}/{c}": row for (s, c), row in seed.items()} for seed in per_seed],
                "by_seed": by_seed,
                "summary": summary,
            },
            indent=1,
        )
        + "\n"
    )


if __name__ == "__main__":
    main()
