"""Issue 13: closest points, distances and signed distances. vkray's `Scene.closest_points`,
`distance` and `signed_distance` at precision "exact" (each backend the device offers, or
--backend) and "reference" against Open3D's RaycastingScene (`compute_closest_points`,
`compute_distance`, `compute_signed_distance`) and trimesh.proximity (`closest_point`,
`signed_distance`), on the same points in one run, numpy in, numpy out. Prints Markdown; `--json`
keeps every figure.

    python benchmarks/bench_distance.py --open3d-python /tmp/o3dvenv/bin/python     # lavapipe: 100k points, both backends
    python benchmarks/bench_distance.py --points 1000000 --sdf-grid 128 --winding-points 10000 --json $OUT/distance.json   # the GPU run

Points, per mesh (the bunny, open: it has holes; fandisk, closed), --points of each kind:
"near": surface samples (area-weighted triangles, uniform barycentrics) plus gaussian noise of
1% of the bounding box's diagonal per coordinate, the SDF-training case; "box": uniform in the
bounding box grown by 10% about its centre. float64, seeds 13 (near) and 14 (box), the same for
every engine.

Engines: vkray exact (per backend) and reference; Open3D 0.20's RaycastingScene on all cores
(nthreads=0), timed on float32 tensors built once outside the timing ("prebuilt") and numpy in →
numpy out (float64 array → float32 tensor → `.numpy()` of every result); its signed distance with
nsamples=1 (its default) and 3 (a vote of 3 rays). Open3D runs in this process where `import
open3d` works, else in a subprocess of --open3d-python (the points travel in a .npz file).
trimesh.proximity on the first --trimesh-points points only (it is slow; one call after a warm-up
call on 16 points, its rate scaled). trimesh's signed distance is positive inside: its sign is
flipped here.

Timing: one warm-up call on 256 points (it compiles pipelines, builds caches), then a call on the
whole batch; where that took longer than --slow seconds it is the figure, else calls for one
second more (the GPU's clocks rise only after 0.2-0.3 s of work) and then the best of --repeat
further calls.

Signs: vkray's sign is `Scene.contains`': parity of one exact ray per point for closed meshes
(fandisk), the generalized winding number for open ones (the bunny). The winding number sums over
the mesh's hierarchy (far nodes by their boundary edges; on the GPU in the GPU tiers, on the CPU
cores in the reference tier), so the bunny's signed distances may be timed (and their signs
compared) on the first --winding-points points only (the reference tier: about 60,000 points/s
on 2 cores, 140,000 on 16). Accuracy:
against vkray reference: max |Δ distance| (Open3D: its float32 answer; closest points:
|‖p − position‖ − reference distance|), the points whose distance is off by more than 1e-6 of the
bounding diagonal (beyond float32 rounding), and the points whose sign differs from vkray exact's.

--sdf-grid G: fandisk's signed distance on a G³ grid over its bounding box grown by 10% (the
points as one (G, G, G, 3) array), per vkray tier and Open3D (nsamples 1 and 3).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
MESHES = ("stanford-bunny", "fandisk")
KINDS = ("near", "box")
GRID_MESH = "fandisk"
WARM = 256


def grown_box(vertices, grow=0.1):
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2 * (1 + grow)
    return centre - half, centre + half


def make_points(vertices, faces, n, kind, seed):
    rng = np.random.default_rng(seed)
    if kind == "box":
        lo, hi = grown_box(vertices)
        return rng.uniform(lo, hi, size=(n, 3))
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(faces), size=n, p=area / area.sum())
    s, r = np.sqrt(rng.random(n))[:, None], rng.random(n)[:, None]
    surface = (1 - s) * a[tri] + s * (1 - r) * b[tri] + s * r * c[tri]
    diagonal = float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))
    return surface + rng.normal(0.0, 0.01 * diagonal, size=(n, 3))


def make_grid(vertices, g):
    lo, hi = grown_box(vertices)
    axes = [np.linspace(lo[k], hi[k], g) for k in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def timed(call, full, small, repeat, slow, settle=1.0):
    """(seconds, answer, calls timed): a warm-up on `small`, a call on `full`, and where that took
    at most `slow` seconds, calls on `full` for `settle` seconds more and then the best of
    `repeat` more. The settling is for the GPU's clocks: an H100 idle for 2 s or more (as it is
    while the CPU tiers and the peers run) spends its first 0.2-0.3 s of work at 345 MHz, a
    quarter of its speed (docs/benchmarks.md, issue 13, session 12), which six calls of 10 ms
    fall inside entirely."""
    call(small)
    start = time.perf_counter()
    answer = call(full)
    times = [time.perf_counter() - start]
    if times[0] <= slow:
        settled = time.perf_counter() + settle
        while time.perf_counter() < settled:
            call(full)
        times = []
        for _ in range(repeat):
            start = time.perf_counter()
            answer = call(full)
            times.append(time.perf_counter() - start)
    return min(times), answer, len(times)


# ------------------------------------------------------------------------------------------------
# Open3D: in this process, or in a subprocess of another interpreter (no vkray needed there).


def open3d_measure(o3d, data, tasks, repeat, slow):
    """(info, answers) of Open3D's queries for `tasks`; `data`: the meshes and points by name."""
    scenes, timings, answers = {}, {}, {}
    tensor = o3d.core.Tensor.from_numpy

    def scene_of(mesh):
        if mesh not in scenes:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(
                tensor(np.ascontiguousarray(data[f"{mesh}__v"], dtype=np.float32)),
                tensor(np.ascontiguousarray(data[f"{mesh}__f"], dtype=np.uint32)),
            )
            scene.compute_distance(tensor(np.zeros((1, 3), np.float32)))  # builds the BVH
            scenes[mesh] = scene
        return scenes[mesh]

    for task in tasks:
        key, scene = task["key"], scene_of(task["mesh"])
        p = data[f"{key}__p"]
        small_np = p.reshape(-1, 3)[:WARM]
        pre = tensor(np.ascontiguousarray(p, dtype=np.float32))
        small = tensor(np.ascontiguousarray(small_np, dtype=np.float32))

        def from_numpy(q):
            return tensor(q.astype(np.float32))

        def run(name, call_pre, call_np):
            sec, out, calls = timed(call_pre, pre, small, repeat, slow)
            timings[f"{key}/{name}/prebuilt"] = sec
            timings[f"{key}/{name}/prebuilt/calls"] = calls
            if call_np is not None:
                timings[f"{key}/{name}/numpy"] = timed(call_np, p, small_np, repeat, slow)[0]
            return out

        for nsamples in (1, 3):
            out = run(
                f"signed{nsamples}",
                lambda q: scene.compute_signed_distance(q, nsamples=nsamples),
                (lambda q: scene.compute_signed_distance(from_numpy(q), nsamples=nsamples).numpy())
                if nsamples == 1
                else None,
            )
            answers[f"{key}__signed{nsamples}"] = out.numpy()
        if task.get("sdf_only"):
            continue
        out = run(
            "distance",
            lambda q: scene.compute_distance(q),
            lambda q: scene.compute_distance(from_numpy(q)).numpy(),
        )
        answers[f"{key}__distance"] = out.numpy()
        out = run(
            "closest",
            lambda q: scene.compute_closest_points(q),
            lambda q: {k: v.numpy() for k, v in scene.compute_closest_points(from_numpy(q)).items()},
        )
        answers[f"{key}__position"] = out["points"].numpy()
    info = {"open3d": o3d.__version__, "cpus": os.cpu_count(), "timings": timings}
    return info, answers


def open3d_worker(inp, outp, repeat, slow):
    import open3d as o3d

    with np.load(inp) as f:
        data = {k: f[k] for k in f.files}
    info, answers = open3d_measure(o3d, data, json.loads(str(data.pop("tasks"))), repeat, slow)
    np.savez(outp, info=json.dumps(info), **answers)


def run_open3d(args, data, tasks):
    """(info, answers, how it ran) of Open3D, or (None, {}, why not)."""
    try:
        import open3d as o3d
    except Exception as e:  # ImportError, or OSError of a missing shared library
        error = f"{type(e).__name__}: {e}"
    else:
        info, answers = open3d_measure(o3d, data, tasks, args.repeat, args.slow)
        return info, answers, "in this process"
    if not args.open3d_python:
        print(f"import open3d failed ({error}) and no --open3d-python: no Open3D figures", file=sys.stderr)
        return None, {}, f"not run: import open3d failed ({error})"
    with tempfile.TemporaryDirectory() as tmp:
        inp, outp = pathlib.Path(tmp) / "in.npz", pathlib.Path(tmp) / "out.npz"
        np.savez(inp, tasks=json.dumps(tasks), **data)
        command = [args.open3d_python, str(pathlib.Path(__file__).resolve()), "--o3d-worker", str(inp), str(outp)]
        command += ["--repeat", str(args.repeat), "--slow", str(args.slow)]
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0:
            print(f"Open3D worker failed ({done.returncode}):\n{done.stderr[-3000:]}", file=sys.stderr)
            return None, {}, f"not run: its worker failed ({done.returncode})"
        with np.load(outp) as out:
            answers = {k: out[k] for k in out.files if k != "info"}
            return json.loads(str(out["info"])), answers, f"in a subprocess ({args.open3d_python})"


# ------------------------------------------------------------------------------------------------
# trimesh on a subset.


def run_trimesh(v, f, points):
    """{seconds and answers of trimesh.proximity on `points`}, or None where trimesh (or the
    r-tree its proximity queries import on first use) is missing."""
    try:
        import trimesh

        mesh = trimesh.Trimesh(v, f, process=False)
        trimesh.proximity.closest_point(mesh, points[:16])  # builds its r-tree
        trimesh.proximity.signed_distance(mesh, points[:16])  # and its ray intersector
    except ImportError as e:
        print(f"no trimesh ({e}): no trimesh figures", file=sys.stderr)
        return None
    start = time.perf_counter()
    position, distance, _ = trimesh.proximity.closest_point(mesh, points)
    closest_s = time.perf_counter() - start
    start = time.perf_counter()
    signed = -trimesh.proximity.signed_distance(mesh, points)  # trimesh: positive inside
    signed_s = time.perf_counter() - start
    return {
        "n": len(points),
        "closest_s": closest_s,
        "signed_s": signed_s,
        "distance": np.asarray(distance),
        "position": np.asarray(position),
        "signed": np.asarray(signed),
        "version": trimesh.__version__,
    }


# ------------------------------------------------------------------------------------------------


def rate(n, sec):
    return None if not sec else n / sec / 1e6


def fmt(x, spec=".3g"):
    return "-" if x is None else format(x, spec)


def max_delta(a, b):
    return float(np.max(np.abs(np.asarray(a, dtype=np.float64) - b))) if len(b) else None


def off_by(a, b, limit):
    return int(np.count_nonzero(np.abs(np.asarray(a, dtype=np.float64) - b) > limit))


def sign_differs(a, b):
    return int(np.count_nonzero((np.asarray(a) < 0) != (np.asarray(b) < 0)))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=float, default=100_000, help="points of each kind per mesh (default 100k)")
    parser.add_argument("--winding-points", type=int, default=2_000, help="signed distances of open meshes on these")
    parser.add_argument("--trimesh-points", type=int, default=2_000)
    parser.add_argument("--sdf-grid", type=int, default=64, help="side G of fandisk's G³ SDF grid (0: none)")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--slow", type=float, default=2.0, help="a call slower than this (s) is timed once")
    parser.add_argument("--backend", choices=("ray_query", "pipeline"), help="default: every backend the device has")
    parser.add_argument("--device", default=None, help="index or name substring (default: vkray's choice)")
    parser.add_argument("--open3d-python", help="an interpreter with open3d, where this one has none")
    parser.add_argument("--json", type=pathlib.Path)
    parser.add_argument("--o3d-worker", nargs=2, metavar=("IN", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.o3d_worker:
        open3d_worker(*args.o3d_worker, args.repeat, args.slow)
        return

    import vkray

    n = int(args.points)
    info = vkray.Device(args.device).info
    if args.backend:
        backends = [args.backend]
    else:
        backends = [b for b, has in (("ray_query", info.ray_query), ("pipeline", info.ray_tracing_pipeline)) if has]
    if not info.shader_float64:
        print(f"{info.name} has no shaderFloat64: no exact tier", file=sys.stderr)
        backends = []
    devices = {b: vkray.Device(args.device, backend=b) for b in backends}
    ref_device = next(iter(devices.values())) if devices else vkray.Device(args.device)
    engines = [(f"{tier} ({b})", tier, d) for tier in ("fast", "exact") for b, d in devices.items()]
    engines.append(("reference", "reference", ref_device))

    meshes, diagonals, data, tasks, cases = {}, {}, {}, [], []
    for name in MESHES:
        v, f = vkray.data.load_mesh(name)
        data[f"{name}__v"], data[f"{name}__f"] = v, f
        meshes[name] = (v, f, {label: dev.scene(dev.mesh(v, f)) for label, _, dev in engines})
        diagonals[name] = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
        for k, kind in enumerate(KINDS):
            key = f"{name}@{kind}"
            data[f"{key}__p"] = make_points(v, f, n, kind, seed=13 + k)
            tasks.append({"key": key, "mesh": name})
            cases.append((name, kind, key))
    if args.sdf_grid:
        v = data[f"{GRID_MESH}__v"]
        data[f"{GRID_MESH}@grid__p"] = make_grid(v, args.sdf_grid)
        tasks.append({"key": f"{GRID_MESH}@grid", "mesh": GRID_MESH, "sdf_only": True})

    def log(msg):
        print(f"  {msg}", file=sys.stderr, flush=True)

    # vkray
    vk = {}
    for name, _, key in cases:
        v, f, scenes = meshes[name]
        p = data[f"{key}__p"]
        closed = next(iter(scenes.values())).instances[0].mesh.is_closed
        w = n if closed else min(n, args.winding_points)
        res = vk[key] = {"closed": closed, "signed_n": w}
        for label, tier, _ in engines:
            scene = scenes[label]
            res[f"{label}/distance"] = timed(
                lambda q: scene.distance(q, precision=tier), p, p[:WARM], args.repeat, args.slow
            )
            res[f"{label}/closest"] = timed(
                lambda q: scene.closest_points(q, precision=tier), p, p[:WARM], args.repeat, args.slow
            )
            res[f"{label}/signed"] = timed(
                lambda q: scene.signed_distance(q, precision=tier), p[:w], p[:WARM], args.repeat, args.slow
            )
            log(f"{key}: vkray {label} done")
    grid = {}
    if args.sdf_grid:
        g = data[f"{GRID_MESH}@grid__p"]
        scenes = meshes[GRID_MESH][2]
        for label, tier, _ in engines:
            scene = scenes[label]
            grid[label] = timed(
                lambda q: scene.signed_distance(q, precision=tier), g, g[0, 0, :WARM], args.repeat, args.slow
            )
            log(f"grid {args.sdf_grid}^3: vkray {label} done")

    # Open3D, trimesh
    o3d_info, o3d_ans, o3d_how = run_open3d(args, data, tasks)
    log(f"Open3D {o3d_how}")
    tm = o3d_info["timings"] if o3d_info else {}
    tri = {}
    for name, _, key in cases:
        v, f, _ = meshes[name]
        tri[key] = run_trimesh(v, f, data[f"{key}__p"][: args.trimesh_points])
        log(f"{key}: trimesh done")

    # Report
    device = ref_device
    host = f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}, numpy {np.__version__}"
    head = (
        f"Device: {device.name} ({', '.join(backends) or 'no exact tier'}; driver {info.driver}); vkray "
        f"{vkray.__version__}; host: {host}"
    )
    tm_version = next((t["version"] for t in tri.values() if t), None)
    others = f"Open3D {o3d_info['open3d']} ({o3d_how}, {o3d_info['cpus']} CPUs, nthreads=0)" if o3d_info else o3d_how
    others = f"Open3D: {others}; trimesh {tm_version or 'missing'}"
    print(f"Command: `python {' '.join(sys.argv)}`\n")
    print(f"{head}\n\n{others}\n")
    print(
        f"Points: {n:,} of each kind per mesh (near: surface + 1% noise; box: uniform in the box grown by 10%). "
        f"Rates in M points/s, numpy in, numpy out; Open3D prebuilt: on float32 tensors built beforehand. "
        f"× Open3D: the best vkray exact rate, and the reference rate, over Open3D's prebuilt rate. "
        f"trimesh: the first {args.trimesh_points:,} points. max |Δ|: against vkray reference.\n"
    )
    exact_labels = [label for label, tier, _ in engines if tier == "exact"]
    report = {"argv": sys.argv, "device": head, "others": others, "points": n, "rows": [], "grid": None}

    def rates(res, what, count):
        out = {label: rate(count, res[f"{label}/{what}"][0]) for label, _, _ in engines}
        best = max((out[label] for label in exact_labels), default=None)
        return out, best

    def against_open3d(key, what):
        """The columns the distance and closest-points tables share, of one mesh and kind of points: the
        report's figures by name, and the table's cells (vkray by engine, Open3D prebuilt and numpy,
        trimesh, × Open3D: the best exact rate and the reference rate over Open3D's prebuilt rate)."""
        res = vk[key]
        r, best = rates(res, what, n)
        pre, num = rate(n, tm.get(f"{key}/{what}/prebuilt")), rate(n, tm.get(f"{key}/{what}/numpy"))
        t = tri[key]
        t_rate = rate(t["n"], t["closest_s"]) if t else None
        x_ex = best / pre if best and pre else None
        x_ref = r["reference"] / pre if pre else None
        figures = {
            "vkray": r,
            "calls": {label: res[f"{label}/{what}"][2] for label, _, _ in engines},
            "o3d_prebuilt": pre,
            "o3d_numpy": num,
            "trimesh": t_rate,
            "x_exact": x_ex,
            "x_reference": x_ref,
        }
        cells = [fmt(r[label]) for label, _, _ in engines] + [fmt(x) for x in (pre, num, t_rate, x_ex, x_ref)]
        return figures, " | ".join(cells)

    # The columns the distance and closest-points tables open with.
    cols = " | ".join(f"vkray {label}" for label, _, _ in engines)
    shared_head = f"| mesh | points | {cols} | Open3D prebuilt | Open3D numpy | trimesh | × Open3D: exact | × Open3D: reference "

    # distance
    print("### distance (M points/s)\n")
    print(
        shared_head + "| max \\|Δ\\|: exact | max \\|Δ\\|: Open3D | max \\|Δ\\|: trimesh | off by > 1e-6 diag: Open3D "
        "| trimesh |"
    )
    print("|---|---|" + "---|" * (len(engines) + 10))
    for name, kind, key in cases:
        res = vk[key]
        figures, cells = against_open3d(key, "distance")
        ref = res["reference/distance"][1]
        t = tri[key]
        d_exact = [max_delta(res[f"{label}/distance"][1], ref) for label in exact_labels]
        d_o3d = max_delta(o3d_ans[f"{key}__distance"], ref) if f"{key}__distance" in o3d_ans else None
        d_tri = max_delta(t["distance"], ref[: t["n"]]) if t else None
        limit = 1e-6 * diagonals[name]
        off_o3d = off_by(o3d_ans[f"{key}__distance"], ref, limit) if f"{key}__distance" in o3d_ans else None
        off_tri = off_by(t["distance"], ref[: t["n"]], limit) if t else None
        of = f" of {t['n']:,}" if t else ""
        print(
            f"| {name} | {kind} | {cells} | "
            f"{fmt(max(d_exact) if d_exact else None, '.1e')} | {fmt(d_o3d, '.1e')} | {fmt(d_tri, '.1e')} | "
            f"{fmt(off_o3d, ',')} | {fmt(off_tri, ',')}{of} |"
        )
        report["rows"].append(
            {
                "query": "distance",
                "mesh": name,
                "kind": kind,
                "n": n,
                **figures,
                "max_delta_exact": dict(zip(exact_labels, d_exact)),
                "max_delta_o3d": d_o3d,
                "max_delta_trimesh": d_tri,
                "off_o3d": off_o3d,
                "off_trimesh": off_tri,
            }
        )

    # closest points
    print(
        "\n### closest points (M points/s; vkray: `closest_points` with its default outputs; Open3D: "
        "`compute_closest_points`, numpy: every result as numpy; trimesh: `proximity.closest_point`)\n"
    )
    print(shared_head + "| max \\|Δ\\| of ‖p − position‖: exact | Open3D | trimesh | ≠ prim_id: exact |")
    print("|---|---|" + "---|" * (len(engines) + 9))
    for name, kind, key in cases:
        res = vk[key]
        p = data[f"{key}__p"]
        figures, cells = against_open3d(key, "closest")
        refc = res["reference/closest"][1]
        ref = refc.distance
        t = tri[key]

        def off(position, count=n):
            return max_delta(np.linalg.norm(p[:count] - position, axis=1), ref[:count])

        d_exact = [off(res[f"{label}/closest"][1].position) for label in exact_labels]
        prim = [int(np.count_nonzero(res[f"{label}/closest"][1].prim_id != refc.prim_id)) for label in exact_labels]
        d_o3d = off(o3d_ans[f"{key}__position"]) if f"{key}__position" in o3d_ans else None
        d_tri = off(t["position"], t["n"]) if t else None
        print(
            f"| {name} | {kind} | {cells} | "
            f"{fmt(max(d_exact) if d_exact else None, '.1e')} | {fmt(d_o3d, '.1e')} | {fmt(d_tri, '.1e')} | "
            f"{fmt(max(prim) if prim else None, ',')} |"
        )
        report["rows"].append(
            {
                "query": "closest_points",
                "mesh": name,
                "kind": kind,
                "n": n,
                **figures,
                "max_delta_exact": dict(zip(exact_labels, d_exact)),
                "prim_differ_exact": dict(zip(exact_labels, prim)),
                "max_delta_o3d": d_o3d,
                "max_delta_trimesh": d_tri,
            }
        )

    # signed distance
    print(
        "\n### signed distance (M points/s; sign ≠: points whose sign differs from vkray exact's, or "
        "reference's where there is no exact tier)\n"
    )
    print(
        f"| mesh | points | vkray sign by | points timed (vkray) | {cols} | Open3D n=1 prebuilt | Open3D n=1 numpy | "
        "Open3D n=3 prebuilt | trimesh | × Open3D n=1: exact | × Open3D n=1: reference | inside (vkray) | "
        "sign ≠: reference | Open3D n=1 | Open3D n=3 | trimesh |"
    )
    print("|---|---|---|---|" + "---|" * (len(engines) + 12))
    for name, kind, key in cases:
        res = vk[key]
        w = res["signed_n"]
        r, best = rates(res, "signed", w)
        truth = res[f"{exact_labels[0]}/signed"][1] if exact_labels else res["reference/signed"][1]
        d_ref = sign_differs(res["reference/signed"][1], truth)
        pre1 = rate(n, tm.get(f"{key}/signed1/prebuilt"))
        num1 = rate(n, tm.get(f"{key}/signed1/numpy"))
        pre3 = rate(n, tm.get(f"{key}/signed3/prebuilt"))
        d_o3d = {
            s: sign_differs(o3d_ans[f"{key}__signed{s}"][:w], truth) if f"{key}__signed{s}" in o3d_ans else None
            for s in (1, 3)
        }
        t = tri[key]
        t_rate = rate(t["n"], t["signed_s"]) if t else None
        tn = min(t["n"], w) if t else 0
        d_tri = sign_differs(t["signed"][:tn], truth[:tn]) if t else None
        x_ex = best / pre1 if best and pre1 else None
        x_ref = r["reference"] / pre1 if pre1 else None
        by = "parity" if res["closed"] else "winding number"
        inside = int(np.count_nonzero(truth < 0))
        print(
            f"| {name} | {kind} | {by} | {w:,} | {' | '.join(fmt(r[label]) for label, _, _ in engines)} | "
            f"{fmt(pre1)} | {fmt(num1)} | {fmt(pre3)} | {fmt(t_rate)} | {fmt(x_ex)} | "
            f"{fmt(x_ref)} | {inside:,} | {d_ref:,} | {fmt(d_o3d[1], ',')} | {fmt(d_o3d[3], ',')} | "
            f"{fmt(d_tri, ',')}{'' if not t or tn == w else f' ({tn:,})'} |"
        )
        report["rows"].append(
            {
                "query": "signed_distance",
                "mesh": name,
                "kind": kind,
                "n": w,
                "sign_by": by,
                "vkray": r,
                "calls": {label: res[f"{label}/signed"][2] for label, _, _ in engines},
                "o3d_prebuilt_1": pre1,
                "o3d_numpy_1": num1,
                "o3d_prebuilt_3": pre3,
                "trimesh": t_rate,
                "trimesh_n": t["n"] if t else None,
                "x_exact": x_ex,
                "x_reference": x_ref,
                "inside": inside,
                "sign_differ_reference": d_ref,
                "sign_differ_o3d_1": d_o3d[1],
                "sign_differ_o3d_3": d_o3d[3],
                "sign_differ_trimesh": d_tri,
            }
        )

    # SDF grid
    if args.sdf_grid:
        g = args.sdf_grid
        count = g**3
        key = f"{GRID_MESH}@grid"
        truth = grid[exact_labels[0]][1] if exact_labels else grid["reference"][1]
        ref = grid["reference"][1]
        print(f"\n### signed distance field: {GRID_MESH} on a {g}³ grid ({count:,} points) over its box grown by 10%\n")
        print("| engine | seconds | M points/s | max \\|Δ\\| vs reference | sign ≠ vkray | inside |")
        print("|---|---|---|---|---|---|")
        rows = []
        for label, _, _ in engines:
            sec, sd, _ = grid[label]
            rows.append(
                (f"vkray {label}", sec, max_delta(sd.reshape(-1), ref.reshape(-1)), sign_differs(sd, truth), sd)
            )
        for s, how in ((1, "prebuilt"), (1, "numpy"), (3, "prebuilt")):
            sec = tm.get(f"{key}/signed{s}/{how}")
            if sec is None:
                continue
            sd = o3d_ans[f"{key}__signed{s}"]
            rows.append(
                (
                    f"Open3D nsamples={s}, {how}",
                    sec,
                    max_delta(sd.reshape(-1), ref.reshape(-1)),
                    sign_differs(sd, truth),
                    sd,
                )
            )
        report["grid"] = {"g": g, "rows": []}
        for label, sec, delta, differ, sd in rows:
            inside = int(np.count_nonzero(sd < 0))
            print(f"| {label} | {sec:.3f} | {rate(count, sec):.3g} | {delta:.1e} | {differ:,} | {inside:,} |")
            report["grid"]["rows"].append(
                {"engine": label, "seconds": sec, "max_delta": delta, "sign_differ": differ, "inside": inside}
            )
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    main()
