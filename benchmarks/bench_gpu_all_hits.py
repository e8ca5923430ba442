"""Issue 10 on a GPU: vkray's `count`, `intersect_all` and `contains` against Open3D's
RaycastingScene (`count_intersections`, `list_intersections`, `compute_occupancy`), on the same
rays and points in one run, plus bytes per stored hit, the largest all-hits query that fits in host
memory and one that does not (MemoryError). Prints Markdown; `--json` keeps every figure.

The figures in docs/benchmarks.md (NVIDIA H100, 16 cores) come from, in the repository root:

    python benchmarks/bench_gpu_all_hits.py --part main --json $OUT/main.json > $OUT/main.md
    python benchmarks/bench_gpu_all_hits.py --part scaling --json $OUT/scaling.json > $OUT/scaling.md
    python benchmarks/bench_gpu_all_hits.py --part big --json $OUT/big.json > $OUT/big.md
    python benchmarks/bench_gpu_all_hits.py --part oom --json $OUT/oom.json > $OUT/oom.md

(There: vkray's wheel and Open3D's ``open3d-cpu`` 0.20 wheel on the machine's Python 3.12 and numpy;
Open3D's import needs ``libusb-1.0.so.0`` and, without plotly, its visualization's plotly import
made optional.)
A dry run on a small device: ``--sizes 2000 10000 --points 20000 --big-rays 50000 --fit-gb 0.02
--scaling 4096x1 1024x4 256x16``.

main: the bunny ("stanford-bunny", open) and fandisk, ``--sizes`` random rays (``oracle.random_rays``,
seed 5); best of ``--repeat`` after one warm-up call of the whole batch; numpy in, numpy out for
vkray (float64 rays, answers as numpy arrays). Open3D runs in a subprocess (``--o3d-python``,
default this interpreter: Open3D and vkray need not share one), timed inside it twice: on tensors
built beforehand ("prebuilt") and numpy in → numpy out (float64 → float32 rays tensor, ``.numpy()``
of every result). Its threads: all cores (nthreads=0). ``contains``: ``--points`` points uniform in
the bounding box of each closed mesh (fandisk, spot, cow). Agreement: rays whose count differs from
vkray's exact `count`, points whose occupancy differs from vkray's exact `contains`.

big: ``--big-rays`` rays at the bunny (`intersect_all`, outputs t and prim_id, fast and exact), then
K identical instances of the bunny (the same rays), K chosen so that the result holds about
``--fit-gb`` GB (default: an eighth of the memory available); one run each, count's time too; peak
resident memory from /proc/self/status (VmHWM reset through /proc/self/clear_refs where allowed).
scaling: intersect_all (fast) against count (fast) as each ray's list grows, the hits held near
constant (``--scaling`` RAYSxCOPIES cases). oom: K copies chosen so that every output of
`intersect_all` needs 1.5× the memory available: it must raise MemoryError (after its counting
pass), and how long that took.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np
from _timing import open3d_scene

ROOT = pathlib.Path(__file__).resolve().parents[1]
MESHES = ("stanford-bunny", "fandisk")
CLOSED = ("fandisk", "spot", "cow")
FIELDS = ["t", "prim_id"]


def best(repeat, fn):
    """(best seconds of `repeat` calls after one warm-up call, the last answer)."""
    answer = fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        answer = fn()
        times.append(time.perf_counter() - start)
    return min(times), answer


# ------------------------------------------------------------------------------------------------
# Open3D, in its own process (no vkray, no oracle there).


def o3d_worker(inp, outp, repeat):
    import open3d as o3d

    data = np.load(inp)
    tasks = json.loads(str(data["tasks"]))
    scenes, timings, answers = {}, {}, {}

    def scene_of(mesh):
        if mesh not in scenes:
            scenes[mesh] = open3d_scene(o3d, data[f"{mesh}__v"], data[f"{mesh}__f"])
        return scenes[mesh]

    for task in tasks:
        key, scene = task["key"], scene_of(task["mesh"])
        if task["kind"] == "rays":
            o, d = data[f"{key}__o"], data[f"{key}__d"]
            rays = o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.hstack([o, d]), dtype=np.float32))

            def numpy_rays():
                return o3d.core.Tensor.from_numpy(np.hstack([o, d]).astype(np.float32))

            sec, counts = best(repeat, lambda: scene.count_intersections(rays))
            timings[f"{key}/count/prebuilt"] = sec
            answers[f"{key}__count"] = counts.numpy().astype(np.int32)
            sec, _ = best(repeat, lambda: scene.count_intersections(numpy_rays()).numpy())
            timings[f"{key}/count/numpy"] = sec
            sec, hits = best(repeat, lambda: scene.list_intersections(rays))
            timings[f"{key}/list/prebuilt"] = sec
            arrays = {name: tensor.numpy() for name, tensor in hits.items()}
            answers[f"{key}__list_counts"] = np.diff(arrays["ray_splits"]).astype(np.int32)
            timings[f"{key}/list/hits"] = int(arrays["t_hit"].shape[0])
            timings[f"{key}/list/bytes"] = int(sum(a.nbytes for a in arrays.values()))
            timings[f"{key}/list/fields"] = {name: str(a.dtype) + str(a.shape[1:]) for name, a in arrays.items()}
            sec, _ = best(repeat, lambda: {k: v.numpy() for k, v in scene.list_intersections(numpy_rays()).items()})
            timings[f"{key}/list/numpy"] = sec
        else:
            p = data[f"{key}__p"]
            points = o3d.core.Tensor.from_numpy(np.ascontiguousarray(p, dtype=np.float32))
            for nsamples in (1, 3):
                sec, occ = best(repeat, lambda: scene.compute_occupancy(points, nsamples=nsamples))
                timings[f"{key}/occupancy{nsamples}/prebuilt"] = sec
                answers[f"{key}__occupancy{nsamples}"] = occ.numpy() > 0.5
                sec, _ = best(
                    repeat,
                    lambda: scene.compute_occupancy(
                        o3d.core.Tensor.from_numpy(p.astype(np.float32)), nsamples=nsamples
                    ).numpy(),
                )
                timings[f"{key}/occupancy{nsamples}/numpy"] = sec
    info = {"open3d": o3d.__version__, "cpus": os.cpu_count(), "timings": timings}
    np.savez(outp, info=json.dumps(info), **answers)


def run_open3d(python, inputs, tasks, repeat):
    """Open3D's timings and answers for `tasks`, or None (with the reason on stderr)."""
    with tempfile.TemporaryDirectory() as tmp:
        inp, outp = pathlib.Path(tmp) / "in.npz", pathlib.Path(tmp) / "out.npz"
        np.savez(inp, tasks=json.dumps(tasks), **inputs)
        command = [python, str(pathlib.Path(__file__).resolve()), "--o3d-worker", str(inp), str(outp)]
        done = subprocess.run([*command, "--repeat", str(repeat)], capture_output=True, text=True)
        if done.returncode != 0:
            print(f"Open3D worker failed ({done.returncode}):\n{done.stderr[-3000:]}", file=sys.stderr)
            return None
        with np.load(outp) as out:
            answers = {k: out[k] for k in out.files if k != "info"}
            return json.loads(str(out["info"])), answers


# ------------------------------------------------------------------------------------------------
# Memory figures.


def status_kb(field):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return None


def reset_peak():
    """Resets VmHWM to the current RSS; False where the kernel does not allow it."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def mem_available():
    with open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no MemAvailable in /proc/meminfo")


def result_bytes(hits):
    """(bytes of the per-ray arrays: offsets, counts; bytes of the per-hit arrays: ray_index and fields)."""
    per_ray = hits.offsets.nbytes + hits.counts.nbytes
    per_hit = hits.ray_index.nbytes + sum(
        getattr(hits, name).nbytes
        for name in ("t", "prim_id", "instance_id", "custom_index", "geometry_id", "uv", "normal", "position")
        if getattr(hits, name) is not None
    )
    return per_ray, per_hit


def field_sizes(hits):
    names = ("ray_index", "t", "prim_id", "instance_id", "custom_index", "geometry_id", "uv", "normal", "position")
    out = {}
    for name in names:
        a = getattr(hits, name)
        if a is not None and len(a):
            out[name] = a.nbytes // len(a)
    return out


# ------------------------------------------------------------------------------------------------


def setup():
    sys.path.insert(0, str(ROOT / "tests"))
    import vkray
    from oracle import load_mesh, random_rays

    return vkray, load_mesh, random_rays


def header(device):
    import vkray

    return (
        f"Device: {device.name} ({device.backend}); vkray {vkray.__version__}; host: {platform.machine()}, "
        f"{os.cpu_count()} CPUs, Python {platform.python_version()}, numpy {np.__version__}"
    )


def rate(n, sec):
    return n / sec / 1e6


def part_main(args, report):
    vkray, load_mesh, random_rays = setup()
    device = vkray.Device()
    print(header(device) + "\n")
    report["device"] = header(device)
    rows, inputs, tasks, vk = [], {}, [], {}
    meshes = {}
    for name in dict.fromkeys(MESHES + CLOSED):
        v, f = load_mesh(name)
        meshes[name] = (v, f, device.mesh(v, f))
        inputs[f"{name}__v"], inputs[f"{name}__f"] = v, f

    # vkray
    for name in MESHES:
        v, f, mesh = meshes[name]
        scene = device.scene(mesh)
        for n in args.sizes:
            key = f"{name}@{n}"
            o, d = random_rays(v, n, seed=5)
            inputs[f"{key}__o"], inputs[f"{key}__d"] = o, d
            tasks.append({"kind": "rays", "key": key, "mesh": name})
            res = vk[key] = {}
            for p in ("fast", "exact"):
                sec, counts = best(args.repeat, lambda: scene.count(o, d, precision=p))
                res[f"count/{p}"] = (sec, counts, device.last_trace_profile)
            tiers = ("fast", "refined", "exact") if n <= args.refined_max else ("fast", "exact")
            for p in tiers:
                sec, hits = best(args.repeat, lambda: scene.intersect_all(o, d, precision=p, outputs=FIELDS))
                per_ray, per_hit = result_bytes(hits)
                res[f"all/{p}"] = (sec, hits.counts.astype(np.int32), device.last_trace_profile)
                res[f"all/{p}/hits"] = len(hits.ray_index)
                res[f"all/{p}/bytes"] = (per_ray, per_hit, field_sizes(hits))
                del hits
            start = time.perf_counter()
            ref = scene.count(o, d, precision="reference")
            res["count/reference"] = (time.perf_counter() - start, ref, None)
    for name in CLOSED:
        v, f, mesh = meshes[name]
        if not mesh.is_closed:
            print(f"{name} is not closed: no contains\n")
            continue
        scene = device.scene(mesh)
        rng = np.random.default_rng(1)
        points = rng.uniform(v.min(axis=0), v.max(axis=0), size=(args.points, 3))
        key = f"{name}@points"
        inputs[f"{key}__p"] = points
        tasks.append({"kind": "points", "key": key, "mesh": name})
        sec, inside = best(args.repeat, lambda: scene.contains(points, precision="exact"))
        vk[key] = {"contains/exact": (sec, inside, device.last_trace_profile)}
        start = time.perf_counter()
        ref = scene.contains(points, precision="reference")
        vk[key]["contains/reference"] = (time.perf_counter() - start, ref, None)

    o3d = run_open3d(args.o3d_python, inputs, tasks, args.repeat) if args.o3d_python else None
    o3d_info, o3d_ans = o3d if o3d else ({"timings": {}}, {})
    tm = o3d_info["timings"]
    if o3d:
        line = (
            f"Open3D {o3d_info['open3d']} (open3d.t.geometry.RaycastingScene, {o3d_info['cpus']} CPUs, nthreads=0: all)"
        )
        print(line + "\n")
        report["open3d"] = line

    def o3d_rate(n, key):
        return rate(n, tm[key]) if key in tm else None

    def fmt(x, spec=".1f"):
        return "-" if x is None else format(x, spec)

    def main_cases(what):
        """Each mesh and ray count of the main part: (mesh, rays, key, vkray's results, vkray's exact
        counts, Open3D's rates of `what` ("count" or "list") on prebuilt tensors and numpy in, numpy out)."""
        for name in MESHES:
            for n in args.sizes:
                key = f"{name}@{n}"
                res = vk[key]
                pre, num = o3d_rate(n, f"{key}/{what}/prebuilt"), o3d_rate(n, f"{key}/{what}/numpy")
                yield name, n, key, res, res["count/exact"][1], pre, num

    # counts
    print("### count (M rays/s; × = vkray / Open3D count_intersections on prebuilt tensors)\n")
    print(
        "| mesh | rays | vkray fast | vkray exact | vkray reference (CPU, 1 run) | Open3D prebuilt | Open3D numpy | × fast | × exact | ≠ exact: fast | ≠ exact: reference | ≠ exact: Open3D |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, n, key, res, exact, pre, num in main_cases("count"):
        fast_r, exact_r = rate(n, res["count/fast"][0]), rate(n, res["count/exact"][0])
        ref_r = rate(n, res["count/reference"][0])
        d_fast = int((res["count/fast"][1] != exact).sum())
        d_ref = int((res["count/reference"][1] != exact).sum())
        d_o3d = int((o3d_ans[f"{key}__count"] != exact).sum()) if f"{key}__count" in o3d_ans else None
        x_fast, x_exact = (fast_r / pre, exact_r / pre) if pre else (None, None)
        print(
            f"| {name} | {n:,} | {fast_r:.1f} | {exact_r:.1f} | {ref_r:.2f} | {fmt(pre)} | {fmt(num)} | "
            f"{fmt(x_fast, '.2f')} | {fmt(x_exact, '.2f')} | {d_fast:,} | {d_ref:,} | {fmt(d_o3d, ',')} |"
        )
        rows.append(
            {
                "query": "count",
                "mesh": name,
                "n": n,
                "vkray_fast": fast_r,
                "vkray_exact": exact_r,
                "vkray_reference": ref_r,
                "o3d_prebuilt": pre,
                "o3d_numpy": num,
                "differ_fast": d_fast,
                "differ_reference": d_ref,
                "differ_o3d": d_o3d,
                "profile_fast": res["count/fast"][2],
                "profile_exact": res["count/exact"][2],
            }
        )

    # all hits
    print(
        "\n### intersect_all, outputs t and prim_id (M rays/s; × = vkray / Open3D list_intersections on prebuilt tensors)\n"
    )
    print(
        "| mesh | rays | hits (exact) | vkray fast | vkray refined | vkray exact | Open3D prebuilt | Open3D numpy | × fast | × exact | ≠ count exact: fast | refined | exact | Open3D |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, n, key, res, exact, pre, num in main_cases("list"):
        r = {p: rate(n, res[f"all/{p}"][0]) if f"all/{p}" in res else None for p in ("fast", "refined", "exact")}
        dif = {p: int((res[f"all/{p}"][1] != exact).sum()) if f"all/{p}" in res else None for p in r}
        lc = o3d_ans.get(f"{key}__list_counts")
        d_o3d = int((lc != exact).sum()) if lc is not None else None
        x_fast, x_exact = (r["fast"] / pre, r["exact"] / pre) if pre else (None, None)
        print(
            f"| {name} | {n:,} | {res['all/exact/hits']:,} | {fmt(r['fast'])} | {fmt(r['refined'])} | {fmt(r['exact'])} | "
            f"{fmt(pre)} | {fmt(num)} | {fmt(x_fast, '.2f')} | {fmt(x_exact, '.2f')} | "
            f"{dif['fast']:,} | {fmt(dif['refined'], ',')} | {dif['exact']:,} | {fmt(d_o3d, ',')} |"
        )
        rows.append(
            {
                "query": "intersect_all",
                "mesh": name,
                "n": n,
                "hits": res["all/exact/hits"],
                **{f"vkray_{p}": r[p] for p in r},
                "o3d_prebuilt": pre,
                "o3d_numpy": num,
                **{f"differ_{p}": dif[p] for p in dif},
                "differ_o3d": d_o3d,
                "o3d_hits": tm.get(f"{key}/list/hits"),
                "o3d_bytes": tm.get(f"{key}/list/bytes"),
                "o3d_fields": tm.get(f"{key}/list/fields"),
                **{f"bytes_{p}": res[f"all/{p}/bytes"] for p in r if f"all/{p}" in res},
                **{f"hits_{p}": res[f"all/{p}/hits"] for p in r if f"all/{p}" in res},
                **{f"profile_{p}": res[f"all/{p}"][2] for p in r if f"all/{p}" in res},
            }
        )

    # contains
    print("\n### contains (M points/s; × = vkray / Open3D compute_occupancy on prebuilt tensors)\n")
    print(
        "| mesh | points | vkray exact | vkray reference (CPU, 1 run) | Open3D n=1 prebuilt | n=1 numpy | n=3 prebuilt | n=3 numpy | × n=1 | × n=3 | ≠ exact: reference | Open3D n=1 | Open3D n=3 |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    n = args.points
    for name in CLOSED:
        key = f"{name}@points"
        if key not in vk:
            continue
        res = vk[key]
        exact = res["contains/exact"][1]
        ex_r, ref_r = rate(n, res["contains/exact"][0]), rate(n, res["contains/reference"][0])
        o = {k: o3d_rate(n, f"{key}/occupancy{k}") for k in ("1/prebuilt", "1/numpy", "3/prebuilt", "3/numpy")}
        d = {
            s: int((o3d_ans[f"{key}__occupancy{s}"] != exact).sum()) if f"{key}__occupancy{s}" in o3d_ans else None
            for s in (1, 3)
        }
        d_ref = int((res["contains/reference"][1] != exact).sum())
        x1 = ex_r / o["1/prebuilt"] if o["1/prebuilt"] else None
        x3 = ex_r / o["3/prebuilt"] if o["3/prebuilt"] else None
        print(
            f"| {name} | {n:,} | {ex_r:.1f} | {ref_r:.2f} | {fmt(o['1/prebuilt'])} | {fmt(o['1/numpy'])} | "
            f"{fmt(o['3/prebuilt'])} | {fmt(o['3/numpy'])} | {fmt(x1, '.2f')} | {fmt(x3, '.2f')} | {d_ref:,} | "
            f"{fmt(d[1], ',')} | {fmt(d[3], ',')} |"
        )
        rows.append(
            {
                "query": "contains",
                "mesh": name,
                "n": n,
                "vkray_exact": ex_r,
                "vkray_reference": ref_r,
                **{f"o3d_{k}": v for k, v in o.items()},
                "differ_reference": d_ref,
                "differ_o3d_1": d[1],
                "differ_o3d_3": d[3],
                "inside": int(exact.sum()),
                "profile_exact": res["contains/exact"][2],
            }
        )

    # bytes per hit
    print("\n### bytes of an intersect_all result (outputs t, prim_id)\n")
    for name in MESHES:
        n = args.sizes[-1]
        res = vk[f"{name}@{n}"]
        for p in ("fast", "exact"):
            per_ray, per_hit = res[f"all/{p}/bytes"][:2]
            hits = res[f"all/{p}/hits"]
            sizes = res[f"all/{p}/bytes"][2]
            print(
                f"- {name}, {n:,} rays, {p}: {hits:,} hits; per ray {per_ray / n:.1f} B (offsets, counts), "
                f"per hit {per_hit / max(hits, 1):.1f} B ({', '.join(f'{k} {v}' for k, v in sizes.items())})"
            )
        lb, lh = tm.get(f"{name}@{n}/list/bytes"), tm.get(f"{name}@{n}/list/hits")
        if lb:
            print(
                f"  Open3D list_intersections: {lh:,} hits, {lb / max(lh, 1):.1f} B per hit all told "
                f"({tm[f'{name}@{n}/list/fields']})"
            )
    report["rows"] = rows


def stacked(device, mesh, copies):
    return device.scene([mesh] * copies)


def part_big(args, report):
    vkray, load_mesh, random_rays = setup()
    device = vkray.Device()
    print(header(device) + "\n")
    avail = mem_available()
    print(f"MemAvailable at start: {avail / 1e9:.1f} GB; VmHWM reset allowed: {reset_peak()}\n")
    v, f = load_mesh("stanford-bunny")
    mesh = device.mesh(v, f)
    scene = device.scene(mesh)
    out = report.setdefault("big", [])

    def measure(label, scene, o, d, precision):
        scene.intersect_all(o[:1000], d[:1000], precision=precision, outputs=FIELDS)  # warm-up
        start = time.perf_counter()
        scene.count(o, d, precision=precision)
        count_sec = time.perf_counter() - start
        rss0 = status_kb("VmRSS")
        reset_ok = reset_peak()
        start = time.perf_counter()
        hits = scene.intersect_all(o, d, precision=precision, outputs=FIELDS)
        sec = time.perf_counter() - start
        peak = status_kb("VmHWM")
        per_ray, per_hit = result_bytes(hits)
        h = len(hits.ray_index)
        row = {
            "label": label,
            "precision": precision,
            "rays": len(o),
            "hits": h,
            "seconds": sec,
            "count_seconds": count_sec,
            "result_gb": (per_ray + per_hit) / 1e9,
            "peak_extra_gb": (peak - rss0) * 1024 / 1e9,
            "peak_reset": reset_ok,
            "profile": device.last_trace_profile,
        }
        print(
            f"| {label} | {precision} | {len(o):,} | {h:,} | {count_sec:.2f} | {sec:.2f} | {h / sec / 1e6:.1f} | "
            f"{row['result_gb']:.2f} | {row['peak_extra_gb']:.2f} |",
            flush=True,
        )
        out.append(row)
        del hits
        return h

    print(
        "| scene | precision | rays | hits | count s | intersect_all s | M hits/s | result GB | peak RSS − RSS before, GB |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    o, d = random_rays(v, args.big_rays, seed=7)
    single = measure("bunny", scene, o, d, "fast")
    measure("bunny", scene, o, d, "exact")
    # K identical copies of the bunny at one place: every hit of one copy is found K times.
    target = args.fit_gb * 1e9 if args.fit_gb else avail / 8
    copies = max(1, math.ceil(target / (16 * max(single, 1))))  # fast: ray_index 8 + t 4 + prim_id 4
    report["stack"] = {"single_hits": single, "copies": copies, "target_gb": target / 1e9}
    measure(f"bunny × {copies} instances", stacked(device, mesh, copies), o, d, "fast")


def part_scaling(args, report):
    """intersect_all's time against count's (its counting pass) as each ray's list grows, the hits
    held near constant: K identical instances of the bunny, rays / K rays."""
    vkray, load_mesh, random_rays = setup()
    device = vkray.Device()
    print(header(device) + "\n")
    v, f = load_mesh("stanford-bunny")
    mesh = device.mesh(v, f)
    out = report.setdefault("scaling", [])
    print(
        "| rays | copies | hits | hits per hit ray | count fast s | intersect_all fast s | M hits/s | intersect_all / count |"
    )
    print("|---|---|---|---|---|---|---|---|")
    started = time.perf_counter()
    for n, copies in args.scaling:
        if time.perf_counter() - started > args.scaling_budget:
            print(f"| {n:,} | {copies} | skipped: past {args.scaling_budget} s |  |  |  |  |  |", flush=True)
            continue
        scene = stacked(device, mesh, copies)
        o, d = random_rays(v, n, seed=9)
        scene.count(o[:1000], d[:1000])
        start = time.perf_counter()
        counts = scene.count(o, d)
        count_sec = time.perf_counter() - start
        count_profile = device.last_trace_profile
        scene.intersect_all(o[:1000], d[:1000], outputs=FIELDS)
        start = time.perf_counter()
        hits = scene.intersect_all(o, d, outputs=FIELDS)
        sec = time.perf_counter() - start
        h, hit_rays = len(hits.ray_index), int((counts > 0).sum())
        print(
            f"| {n:,} | {copies} | {h:,} | {h / max(hit_rays, 1):.1f} | {count_sec:.3f} | {sec:.3f} | "
            f"{h / sec / 1e6:.1f} | {sec / count_sec:.1f} |",
            flush=True,
        )
        out.append(
            {
                "rays": n,
                "copies": copies,
                "hits": h,
                "count_seconds": count_sec,
                "seconds": sec,
                "count_profile": count_profile,
                "profile": device.last_trace_profile,
            }
        )
        del hits, scene


def part_oom(args, report):
    vkray, load_mesh, random_rays = setup()
    device = vkray.Device()
    print(header(device) + "\n")
    avail = mem_available()
    v, f = load_mesh("stanford-bunny")
    mesh = device.mesh(v, f)
    o, d = random_rays(v, args.stack_rays, seed=9)
    scene = device.scene(mesh)
    small = scene.intersect_all(o[:20000], d[:20000], precision="fast", outputs=list(vkray.HIT_FIELDS))
    per_hit = result_bytes(small)[1] / max(len(small.ray_index), 1)
    single = int(scene.count(o, d, precision="fast").sum())
    copies = math.ceil(1.5 * avail / (per_hit * max(single, 1)))
    print(
        f"MemAvailable {avail / 1e9:.1f} GB; every output: {per_hit:.1f} B per hit; {single:,} hits on one copy; "
        f"{copies} copies → {copies * single:,} hits, {copies * single * per_hit / 1e9:.0f} GB\n",
        flush=True,
    )
    big = stacked(device, mesh, copies)
    start = time.perf_counter()
    try:
        hits = big.intersect_all(o, d, precision="fast", outputs=list(vkray.HIT_FIELDS))
        outcome = f"no error: {len(hits.ray_index):,} hits"
    except MemoryError as e:
        outcome = f"MemoryError: {e}"
    sec = time.perf_counter() - start
    print(f"{outcome}\nafter {sec:.2f} s; peak RSS of the process {status_kb('VmHWM') / 1e6:.2f} GB")
    report["oom"] = {
        "copies": copies,
        "hits_expected": copies * single,
        "bytes_per_hit": per_hit,
        "gb_expected": copies * single * per_hit / 1e9,
        "available_gb": avail / 1e9,
        "outcome": outcome,
        "seconds": sec,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", choices=("main", "big", "scaling", "oom"), default="main")
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--points", type=int, default=1_000_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--refined-max", type=int, default=100_000, help="refined tier up to this many rays")
    parser.add_argument("--o3d-python", default=sys.executable, help="interpreter with open3d ('' skips Open3D)")
    parser.add_argument("--big-rays", type=int, default=16_000_000)
    parser.add_argument("--stack-rays", type=int, default=1_000_000)
    parser.add_argument(
        "--fit-gb", type=float, default=None, help="result size of the stacked query (default: available/4)"
    )
    parser.add_argument(
        "--scaling",
        type=lambda x: tuple(int(float(a)) for a in x.split("x")),
        nargs="+",
        default=[
            (1 << 20, 1),
            (1 << 22, 1),
            (1 << 24, 1),
            (1 << 23, 8),
            (1 << 21, 32),
            (1 << 20, 64),
            (1 << 18, 256),
            (1 << 16, 1024),
            (1 << 14, 4096),
        ],
        help="RAYSxCOPIES cases of --part scaling",
    )
    parser.add_argument("--scaling-budget", type=float, default=120, help="seconds after which cases are skipped")
    parser.add_argument("--json", type=pathlib.Path)
    parser.add_argument("--o3d-worker", nargs=2, metavar=("IN", "OUT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.o3d_worker:
        o3d_worker(*args.o3d_worker, args.repeat)
        return
    report = {"argv": sys.argv}
    {"main": part_main, "big": part_big, "scaling": part_scaling, "oom": part_oom}[args.part](args, report)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    main()
