"""Calibrate each front end's along-axis sigma against ground truth (moment matching).

Reads the ``factor_consistency`` of runs with ground truth — rows of
``benchmarks/estimator.py --json`` files, or ``metrics.json`` files of ``jaxslam run`` — pools
each kind's along-axis z RMS over them (weighted by measurement count) and writes the
``{lidar,vision,loop}.axis_sigma_scale`` and ``loop.visual_axis_sigma_scale`` that would
make it 1.0, as a config for
``jaxslam run --config`` / ``benchmarks/estimator.py --config``::

    python benchmarks/calibrate_axis.py runs/train_*.json -o runs/axis_calibrated.yaml

``--config`` names the configuration the runs were made with (its scales are multiplied).
Calibrate on training recordings and judge the result on others: the scales are fitted to
the runs they are read from.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="estimator benchmark JSON files or metrics.json files")
    ap.add_argument("-o", "--output", required=True, help="YAML config to write")
    ap.add_argument("--config", metavar="YAML", help="the configuration the runs were made with")
    ap.add_argument("--min-measurements", type=int, default=30)
    args = ap.parse_args()

    from jaxslam.errors import JaxSlamError
    from jaxslam.pipeline._config import PipelineConfig, load_config
    from jaxslam.pipeline._run import AXIS_SCALE_KINDS, axis_sigma_calibration

    try:
        base = load_config(args.config) if args.config else PipelineConfig()
        consistencies, names = [], []
        for path in args.runs:
            p = Path(path)
            try:
                data = json.loads(p.read_text())
            except (OSError, json.JSONDecodeError) as e:
                raise SystemExit(f"{p}: expected a JSON file of estimator runs ({e})") from None
            rows = data if isinstance(data, list) else [data]
            for i, row in enumerate(rows):
                cons = row.get("factor_consistency") if isinstance(row, dict) else None
                if not cons:
                    raise SystemExit(f"{p}[{i}]: no factor_consistency (a run without ground truth at the keyframes?)")
                consistencies.append(cons)
                names.append(f"{p.name}[{i}]" if len(rows) > 1 else p.name)
        for cons, name in zip(consistencies, names):
            print(
                f"{name:<32}"
                + "  ".join(
                    f"{kind} z {cons[kind]['axis_z_rms']:.2f} (n {cons[kind]['measurements']})"
                    for kind in AXIS_SCALE_KINDS.values()
                    if kind in cons and cons[kind].get("axis_z_rms") is not None
                )
            )
        out = axis_sigma_calibration(consistencies, base, args.min_measurements)
    except JaxSlamError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(1) from None
    for (section, field), kind in AXIS_SCALE_KINDS.items():
        old = getattr(getattr(base, section), field)
        new = out.get(section, {}).get(field)
        print(f"{section}.{field} ({kind}): {old:.3f} -> " + (f"{new:.3f}" if new else "kept (too few)"))
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    merged = {s: {**v} for s, v in out.items()}
    if args.config:  # keep the rest of the base configuration
        extra = yaml.safe_load(Path(args.config).read_text()) or {}
        for s, v in extra.items():
            merged[s] = {**(v or {}), **merged.get(s, {})}
    Path(args.output).write_text(yaml.safe_dump(merged, sort_keys=False))
    print(f"wrote {args.output} from {len(consistencies)} run(s)")


if __name__ == "__main__":
    main()
