"""Where a jaxslam kernel spends its time, op by op (XLA:CPU thunks), for performance work.

    python benchmarks/op_profile.py TARGET [--repeats 5] [--top 25] [--loops] [--json PATH]
    taskset -c 0 python benchmarks/op_profile.py TARGET   # one core: no overlap between ops

TARGET: ``surf`` (``jaxslam.vision.surf`` on the KITTI frame, descriptors in parts),
``surf-detect`` (detection + orientation, one call), ``describe`` (the descriptors, one
call), ``imu`` (``preintegrate`` on GTSAM's KITTI IMU stream, one call; needs gtsam).

The kernel runs once to compile, then ``--repeats`` times under ``jax.profiler``; the trace
is read back with ``jax.profiler.ProfileData`` and every event is summed by name (a fused
loop, a custom call such as ``top_k``, a ``while`` loop including its body, or a Python
frame such as ``block_until_ready``). Prints milliseconds per call, largest first, beside
the wall time per call. Ops that run on XLA's worker threads overlap when more than one core
is free, so their sum can exceed the wall time. This profile found a fused NMS loop that
XLA:CPU had made scalar (8 ms of a 30 ms detection on one core, session 29).

``--loops`` also says, for each fused op, whether XLA:CPU's compiled loop is vectorised: it
dumps XLA's optimised LLVM IR (``--xla_dump_to``, a temporary folder, set before JAX starts)
and looks for vector instructions in each op's kernel. A ``scalar`` loop among the largest
ops is the thing to fix; in session 30 they came from a flattening reshape or a dynamic
slice (a ``lax.map`` block, a ``lax.scan`` step) fused into the loop. JSON:
``{"target", "repeats", "wall_ms_per_call", "ops": [{"name", "ms_per_call", "count_per_call"
[, "loop"]}]}``.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

import jaxslam  # noqa: F401  (float64)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TARGETS = ("surf", "surf-detect", "describe", "imu")


def op_profile(fn: Callable[[], object], repeats: int = 5) -> dict:
    """Run ``fn`` once (compile), then ``repeats`` times under the profiler. Returns the
    wall time per call and the events summed by name, per call, largest first. A name's
    numeric suffix (``fusion.12``) is kept: each is a different op."""
    jax.block_until_ready(fn())
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        jax.profiler.start_trace(tmp)
        try:
            for _ in range(repeats):
                jax.block_until_ready(fn())
        finally:
            jax.profiler.stop_trace()
        wall = (time.perf_counter() - t0) / repeats
        traces = sorted(Path(tmp).rglob("*.xplane.pb"))
        if not traces:
            raise RuntimeError(f"the profiler wrote no trace under {tmp}")
        data = jax.profiler.ProfileData.from_file(str(traces[0]))
        total: collections.Counter[str] = collections.Counter()
        count: collections.Counter[str] = collections.Counter()
        for plane in data.planes:
            for line in plane.lines:
                for ev in line.events:
                    total[ev.name] += ev.duration_ns
                    count[ev.name] += 1
    ops = [
        {"name": name, "ms_per_call": ns / repeats / 1e6, "count_per_call": count[name] / repeats}
        for name, ns in total.most_common()
    ]
    return {"repeats": repeats, "wall_ms_per_call": 1e3 * wall, "ops": ops}


_VECTOR_OP = re.compile(
    r"(?:= (?:load|f?add|f?sub|f?mul|fdiv|fcmp|icmp|select|and|or|shl|lshr|sitofp|fptosi)\b[^\n]*|\bstore )<\d+ x "
)


def loop_kind(ir: str) -> str:
    """``vector`` if an op's optimised LLVM IR computes on vectors (four or more vector
    instructions), else ``scalar``."""
    return "vector" if len(_VECTOR_OP.findall(ir)) >= 4 else "scalar"


def loop_kinds(dump: Path) -> dict[str, str]:
    """Op name -> :func:`loop_kind` from XLA:CPU's dump folder (``*_kernel_module.ir-with-opt.ll``
    files, one per fused op and program); the program with the most kernels wins a name."""
    programs: dict[str, dict[str, str]] = collections.defaultdict(dict)
    for f in dump.glob("*_kernel_module.ir-with-opt.ll"):
        module, _, rest = f.name.partition(".")
        program, _, op = rest.partition(".")
        programs[f"{module}.{program}"][op.removesuffix("_kernel_module.ir-with-opt.ll")] = loop_kind(f.read_text())
    out: dict[str, str] = {}
    for kinds in sorted(programs.values(), key=len):
        out.update(kinds)
    return out


# Bookkeeping events of the runtime and of this script, left out of the table.
_SKIP = re.compile(r"ThunkExecutor|ExecuteHelper|PjitFunction|^\$|stop_trace|start_trace")


def _kitti_frame() -> np.ndarray:
    from PIL import Image

    path = DATA / "kitti_mono" / "image_l" / "000000.png"
    if not path.is_file():
        raise SystemExit(f"op_profile: {path} not found (the shared data folder beside the checkout)")
    with Image.open(path) as im:
        return np.asarray(im.convert("L"))


def kernel(target: str) -> Callable[[], object]:
    """The call to profile for ``target`` (inputs prepared once, outside the timing)."""
    if target in ("surf", "surf-detect", "describe"):
        import jax.numpy as jnp

        from jaxslam.vision import surf
        from jaxslam.vision._surf import describe_jit, layer_plan, max_window, surf_u8

        frame = _kitti_frame()
        img = jnp.asarray(frame)
        if target == "surf":
            return lambda: surf(frame, 100.0, max_keypoints=4096)
        if target == "surf-detect":
            return lambda: surf_u8(img, 100.0, max_keypoints=4096, descriptors=False)
        kp, _, valid = surf_u8(img, 100.0, max_keypoints=4096, descriptors=False)
        mw = max_window(layer_plan(*frame.shape, 4, 3))
        cols = (kp[:, 0], kp[:, 1], kp[:, 2], kp[:, 3], valid)
        return lambda: describe_jit(img, *cols, upright=False, max_win=mw)
    if target == "imu":
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from imu_preintegration import BIAS_HAT, kitti_params, load_kitti  # needs gtsam's data

        from jaxslam.factors import cut_imu_stream, preintegrate

        t, acc, gyro, meta = load_kitti()
        iv = cut_imu_stream(t, acc, gyro, np.arange(t[0], t[-1], 0.1))
        params = kitti_params(meta)
        return lambda: preintegrate(iv.acc, iv.gyro, iv.dt, params, BIAS_HAT, iv.mask, parallel=False)
    raise SystemExit(f"op_profile: unknown target {target!r} (expected one of {', '.join(TARGETS)})")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("target", choices=TARGETS)
    ap.add_argument("--repeats", type=int, default=5, help="profiled calls (after the compiling one)")
    ap.add_argument("--top", type=int, default=25, help="rows to print")
    ap.add_argument("--loops", action="store_true", help="say whether each op's compiled loop is vectorised")
    ap.add_argument("--json", type=Path, default=None, help="write the profile here")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    with tempfile.TemporaryDirectory() as dump:
        if args.loops:
            if jax._src.xla_bridge.backends_are_initialized():  # type: ignore[attr-defined]
                raise SystemExit("op_profile: --loops must be set before JAX starts (run it as a script)")
            os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={dump}".strip()
        prof = op_profile(kernel(args.target), args.repeats)
        kinds = loop_kinds(Path(dump)) if args.loops else {}
    for op in prof["ops"]:
        if op["name"] in kinds:
            op["loop"] = kinds[op["name"]]
    prof["target"] = args.target
    print(f"{args.target}: {prof['wall_ms_per_call']:.2f} ms per call (wall, under the profiler)")
    print(f"{'ms/call':>9}  {'n/call':>6}  {'loop  ' if args.loops else ''}op")
    shown = [op for op in prof["ops"] if not _SKIP.search(op["name"])][: args.top]
    for op in shown:
        loop = f"{op.get('loop', '-'):6}  " if args.loops else ""
        print(f"{op['ms_per_call']:9.3f}  {op['count_per_call']:6.1f}  {loop}{op['name']}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(prof, indent=1))
        print(f"wrote {args.json}")
    return prof


if __name__ == "__main__":
    main()
