"""What each effect costs: one row per effect a scene or a query can call for, measured in one run
on the same rays, on every backend the device offers. Prints Markdown; `--json` keeps every figure.

    python benchmarks/bench_effects.py                                   # lavapipe: 200k rays, both backends
    python benchmarks/bench_effects.py --rays 1000000 --backend pipeline --big --json out.json   # the GPU run

Rays (the same for every row but the camera rows): half from a pinhole camera 2.5 bounding radii
from the mesh's centre looking at it (as tests/oracle.py's camera_rays), half from a sphere of 2
bounding radii towards random points of its bounding box, a quarter of those in random directions
(oracle.random_rays, seed 11); float32, uploaded each call. Default 200,000 rays: lavapipe traces
about 1M rays/s on 2 cores, and the whole run stays within a few minutes there; on a GPU use 1M or
more.

Rows (each names the row it is compared with, "vs"):

- baseline: `intersect(outputs=["t"])` on the opaque mesh.
- all fields: `intersect()` with its default outputs (t, prim_id, instance_id, custom_index, uv, normal).
- cull back: `cull="back"` (hits change: back faces are skipped).
- per-ray masks: `mask=` a uint8 array of 0xFF, one per ray (the hits cannot change).
- spheres present: the scene plus 8 small spheres 100 bounding radii away at the corners of a cube
  centred on the mesh (no ray comes near them).
- opacity present: the same mesh with opacity 1 on every triangle but triangle 0 (0.5: not below the
  threshold, so it still blocks and every hit is the baseline's), against the opaque mesh: the
  any-hit stage (pipeline) or the candidate confirmation (ray query) runs on every candidate.
- occluded, intersect_all (outputs ["t"]), count: against the closest hit.
- transmittance on the opacity scene, and on the opaque scene (which has no opacity to multiply).
- camera, uploaded rays: `intersect(*camera.rays(), outputs=["t"])` with a camera of about --rays
  pixels (the arrays are made once, outside the timing); camera, GPU rays: `intersect(camera,
  outputs=["t"])`, nothing uploaded, against the uploaded rays (the same rays bit for bit).

Each row: one warm-up call (it compiles the variant), then --repeat rounds; a round calls every row
once, in order, so drift of the machine spreads over all rows. Reported: the median wall time of a
call (numpy in, numpy out), its rate, and the median GPU trace time (`Device.last_trace_profile`
["gpu_trace"]: timestamps around the trace alone, summed over chunks; for intersect_all both
passes). "x wall" and "x GPU" are the row's time over its "vs" row's: the cost of the effect. "≠"
counts rays whose answer (t where both rows have it, else hit or miss) differs from the vs row's.
The stages, branches and flags come from `Scene.explain` for the row's query.

--big adds the 4096 x 4096 depth image (outputs ["t"]) of a GPU-generated camera: rays per second
end to end (the call's wall clock, the answer as numpy) and of the trace alone.

--tiers adds a table per backend of the precision tiers (fast, refined, exact, reference) of the
newer queries, in a scene of its own: the translucent bunny (opacity uniform in [0, 1) per triangle,
a fifth of them cut-outs at 0; seed 7). `transmittance(o, d, precision=p)` on --tier-rays rays made
as the main rows' are (half camera, half random, seed 11; the very same rays where --tier-rays equals
--rays), and `intersect(camera, outputs=["t", "prim_id"], precision=p)` with a GPU-generated pinhole
camera of about --tier-rays pixels. Each tier: one warm-up call, then max(3, --repeat) rounds of
every tier in order (a reference call slower than --slow-reference seconds is timed once, by its
warm-up); the median wall time, Mrays/s, the GPU trace time, the host's f64 time, "× fast" (wall
time over the fast tier's), and the answer against the reference tier's: max |Δ| of the
transmittance (or of t, where both name the same triangle), rays with |Δ| > 1e-6, and rays whose
answer differs at all (f64 tiers: the transmittance bit for bit; intersect: prim_id). --tiers-only
runs the tier table alone.

    python benchmarks/bench_effects.py --tiers-only                                    # lavapipe: 100k rays, both backends
    python benchmarks/bench_effects.py --tiers-only --tier-rays 1000000 --backend pipeline --json tiers.json   # the GPU run
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import statistics
import sys
import time

import numpy as np
from _report import table_head

import vkray

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "tests"))
from oracle import bounds  # noqa: E402
from oracle import camera_rays as oracle_camera_rays  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]

# Short names for Scene.explain's stages and ray-query branches (anything else is printed whole).
STAGES = {
    "ray generation": "rgen",
    "miss": "miss",
    "closest-hit": "chit",
    "any-hit (opacity)": "ahit(opacity)",
    "any-hit (every hit)": "ahit(every hit)",
    "intersection (spheres)": "isect(spheres)",
    "compute (ray query)": "compute",
    "intersection (exact f64 test)": "isect(f64 test)",
    "host: f64 watertight test on all CPU cores": "host f64 (CPU)",
}
BRANCHES = {
    "boxes: spheres intersected and committed": "spheres",
    "triangles: non-opaque candidates confirmed where their opacity reaches the threshold": "opacity confirm",
    "triangles: every candidate kept (all hits, counts)": "keep every candidate",
    "triangles: every candidate multiplies the light left": "multiply light",
    "boxes: the f64 test of each box's triangle": "f64 test per box",
}
TIERS = ("fast", "refined", "exact", "reference")


def load_mesh(name_or_path):
    """(vertices float64 (V, 3), faces int64 (F, 3)) of a shipped mesh's name (vkray.data), or of a
    mesh file trimesh reads."""
    if name_or_path in vkray.data.MESH_NAMES:
        return vkray.data.load_mesh(name_or_path)
    import trimesh

    loaded = trimesh.load(name_or_path, process=False, force="mesh")
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, dtype=np.int64)


FORWARD = np.array([0.3, -0.4, -1.0]) / np.linalg.norm([0.3, -0.4, -1.0])


def random_rays(vertices, n, seed):
    """tests/oracle.py's random_rays: from a sphere of 2 radii towards the bounding box, a quarter wild."""
    rng = np.random.default_rng(seed)
    centre, radius = bounds(vertices)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    u = rng.normal(size=(n, 3))
    origins = centre + 2.0 * radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    directions = rng.uniform(lo, hi, size=(n, 3)) - origins
    wild = rng.random(n) < 0.25
    directions[wild] = rng.normal(size=(int(wild.sum()), 3))
    return origins, directions


def pinhole(vertices, width, height):
    """A vkray.PinholeCamera with camera_rays' view: 2.5 radii away, 53.13 degrees across."""
    centre, radius = bounds(vertices)
    return vkray.PinholeCamera(
        width,
        height,
        fov_deg=math.degrees(2 * math.atan(0.5)),
        eye=centre - 2.5 * radius * FORWARD,
        target=centre,
        up=[0.0, -1.0, 0.0],  # Open3D's camera y points down the image: world down for upright images
    )


def shorten(explained):
    """(stages, flags) of a Scene.explain answer, as short strings for the table."""
    stages = [STAGES.get(s, s) for s in explained["stages"]]
    branches = [BRANCHES.get(b, b) for b in explained["ray_query_branches"]]
    if branches:
        stages.append("[" + ", ".join(branches) + "]")
    flags = " ".join(explained["ray_flags"]) or "none"
    if explained["pipeline_flags"]:
        flags += "; pipeline: " + " ".join(explained["pipeline_flags"])
    return " ".join(stages), flags


def answer(result):
    """(t or None, hit mask) of any query's result, flattened."""
    if isinstance(result, vkray.Hits):
        t = None if result.t is None else result.t.reshape(-1)
        return t, result.hit.reshape(-1)
    if isinstance(result, vkray.AllHits):
        return None, result.counts.reshape(-1) > 0
    result = np.asarray(result).reshape(-1)
    if result.dtype == np.bool_:  # occluded
        return None, result
    if result.dtype.kind == "f":  # transmittance: 0 where an opaque surface blocks the ray
        return None, result < 1
    return None, result > 0  # count


def differ(a, b):
    """How many rays answer differently (t where both hold it, else hit or miss)."""
    (ta, ha), (tb, hb) = a, b
    if len(ha) != len(hb):
        return None
    if ta is not None and tb is not None:
        return int(np.count_nonzero(~((ta == tb) | (np.isnan(ta) & np.isnan(tb)))))
    return int(np.count_nonzero(ha != hb))


def bench_backend(backend, args, vertices, faces, rays, tier_rays):
    device = vkray.Device(args.device, backend=backend)
    report = {
        "backend": backend,
        "device": device.name,
        "device_type": device.info.device_type,
        "driver": device.info.driver,
        "rows": [],
        "big": None,
        "tiers": None,
    }
    if rays is not None:
        report.update(bench_rows(device, args, vertices, faces, *rays))
    if tier_rays is not None:
        report["tiers"] = bench_tiers(device, args, vertices, faces, *tier_rays)
    return report


def bench_rows(device, args, vertices, faces, o32, d32):
    """The main rows (and --big): {"rows": [...], "big": ...}."""
    backend = device.backend
    n = len(o32)
    centre, radius = bounds(vertices)
    mesh = device.mesh(vertices, faces)
    opacity = np.ones(len(faces), np.float32)
    opacity[0] = 0.5
    translucent = device.mesh(vertices, faces, opacity=opacity)
    # 8 spheres at the corners of a cube 100 radii across, centred on the mesh: the scene's bounds
    # keep their centre, which the TLAS is re-centred on (spheres on one side would move that frame
    # and change the f32 rounding of every t; see docs/effects.md).
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    spheres = device.spheres(centre + 100 * radius / math.sqrt(3) * corners, 0.01 * radius)
    scene = device.scene(mesh)
    scene_spheres = device.scene([mesh, spheres])
    scene_opacity = device.scene(translucent)
    masks = np.full(n, 0xFF, np.uint8)
    side = max(1, int(round(math.sqrt(n))))
    camera = pinhole(vertices, side, side)
    cam_o, cam_d = camera.rays()

    t = ["t"]

    def row(name, query, sc, call, vs="baseline", **explain):
        """(name, query, scene, call, explain kwargs, vs): `call(sc)` is timed, `sc.explain(kind, **explain)`
        (kind an entry of explain, default "closest") names its stages; vs: the row it is compared with."""
        return name, query, sc, lambda: call(sc), explain, vs

    rows = [
        row("baseline", "intersect t", scene, lambda s: s.intersect(o32, d32, outputs=t), vs=None, outputs=t),
        row("all fields", "intersect (6 fields)", scene, lambda s: s.intersect(o32, d32)),
        row("cull back", "intersect t, cull=back", scene, lambda s: s.intersect(o32, d32, outputs=t, cull="back"),
            outputs=t, cull="back"),
        row("per-ray masks", "intersect t, mask=uint8[N]", scene,
            lambda s: s.intersect(o32, d32, outputs=t, mask=masks), outputs=t),
        row("spheres present", "intersect t", scene_spheres, lambda s: s.intersect(o32, d32, outputs=t), outputs=t),
        row("opacity present", "intersect t", scene_opacity, lambda s: s.intersect(o32, d32, outputs=t), outputs=t),
        row("occluded", "occluded", scene, lambda s: s.occluded(o32, d32), kind="occluded"),
        row("all hits", "intersect_all t", scene, lambda s: s.intersect_all(o32, d32, outputs=t), kind="all"),
        row("count", "count", scene, lambda s: s.count(o32, d32), kind="count"),
        row("transmittance (opacity)", "transmittance", scene_opacity, lambda s: s.transmittance(o32, d32),
            kind="transmittance"),
        row("transmittance (opaque)", "transmittance", scene, lambda s: s.transmittance(o32, d32),
            kind="transmittance"),
        row("camera, uploaded rays", f"intersect t, camera.rays() {side}x{side}", scene,
            lambda s: s.intersect(cam_o, cam_d, outputs=t), outputs=t),
        row("camera, GPU rays", f"intersect t, camera {side}x{side}", scene, lambda s: s.intersect(camera, outputs=t),
            vs="camera, uploaded rays", outputs=t, sensor=True),
    ]
    results = []
    for name, query, sc, call, explain_kwargs, vs in rows:
        kind = explain_kwargs.pop("kind", "closest")
        explained = sc.explain(kind, **explain_kwargs)
        first = call()  # warm-up: compiles the variant
        count = camera.width * camera.height if name.startswith("camera") else n
        results.append(
            {
                "name": name,
                "query": query,
                "vs": vs,
                "rays": count,
                "explain": explained,
                "answer": answer(first),
                "call": call,
                "seconds": [],
                "profiles": [],
            }
        )
        print(f"  {backend}: {name} warmed up", file=sys.stderr, flush=True)
    for round_ in range(args.repeat):
        for row in results:
            start = time.perf_counter()
            row["call"]()
            row["seconds"].append(time.perf_counter() - start)
            row["profiles"].append(device.last_trace_profile)
        print(f"  {backend}: round {round_ + 1}/{args.repeat} done", file=sys.stderr, flush=True)

    by_name = {row["name"]: row for row in results}
    for row in results:
        row["median_s"] = statistics.median(row["seconds"])
        traces = [p.get("gpu_trace") for p in row["profiles"]]
        row["gpu_trace_s"] = None if any(x is None for x in traces) else statistics.median(traces)
        row["hit_fraction"] = float(row["answer"][1].mean())
    for row in results:
        ref = by_name.get(row["vs"])
        row["x_wall"] = row["x_gpu"] = row["differ"] = None
        if ref is not None:
            # Cost per ray, so that rows of different ray counts (the camera) compare too.
            row["x_wall"] = (row["median_s"] / row["rays"]) / (ref["median_s"] / ref["rays"])
            if row["gpu_trace_s"] and ref["gpu_trace_s"]:
                row["x_gpu"] = (row["gpu_trace_s"] / row["rays"]) / (ref["gpu_trace_s"] / ref["rays"])
            row["differ"] = differ(row["answer"], ref["answer"])

    big = bench_big(device, scene, vertices, args) if args.big else None
    return {"rows": [{k: v for k, v in row.items() if k not in ("call", "answer")} for row in results], "big": big}


def tier_opacity(count):
    """The translucent bunny's opacity: uniform in [0, 1) per triangle, a fifth cut out (0); seed 7."""
    rng = np.random.default_rng(7)
    opacity = rng.random(count).astype(np.float32)
    opacity[rng.random(count) < 0.2] = 0.0
    return opacity


def bench_tiers(device, args, vertices, faces, o32, d32):
    """Every tier of transmittance (rays from arrays) and of intersect (rays from a GPU camera)."""
    backend = device.backend
    opacity = tier_opacity(len(faces))
    scene = device.scene(device.mesh(vertices, faces, opacity=opacity))
    side = max(1, int(round(math.sqrt(len(o32)))))
    camera = pinhole(vertices, side, side)
    fields = ["t", "prim_id"]
    tiers = [p for p in TIERS if p != "exact" or device.info.shader_float64]
    rows = []
    for query in ("transmittance", "intersect camera"):
        for tier in tiers:
            if query == "transmittance":
                call = lambda p=tier: scene.transmittance(o32, d32, precision=p)  # noqa: E731
                explained = scene.explain("transmittance", precision=tier)
                rays = len(o32)
            else:
                call = lambda p=tier: scene.intersect(camera, outputs=fields, precision=p)  # noqa: E731
                explained = scene.explain("closest", fields, precision=tier, sensor=True)
                rays = camera.width * camera.height
            start = time.perf_counter()
            first = call()  # warm-up: compiles the variant (and the answer compared with the reference's)
            warm_s = time.perf_counter() - start
            once = tier == "reference" and warm_s > args.slow_reference
            rows.append(
                {
                    "query": query,
                    "tier": tier,
                    "rays": rays,
                    "explain": explained,
                    "first": first,
                    "call": call,
                    "once": once,
                    "seconds": [warm_s] if once else [],
                    "profiles": [device.last_trace_profile] if once else [],
                }
            )
            print(f"  {backend}: tiers: {query} {tier} warmed up ({warm_s:.2f} s)", file=sys.stderr, flush=True)
    rounds = max(3, args.repeat)
    for round_ in range(rounds):
        for row in rows:
            if row["once"]:
                continue
            start = time.perf_counter()
            row["call"]()
            row["seconds"].append(time.perf_counter() - start)
            row["profiles"].append(device.last_trace_profile)
        print(f"  {backend}: tiers: round {round_ + 1}/{rounds} done", file=sys.stderr, flush=True)

    def median_of(row, key):
        values = [p.get(key) for p in row["profiles"]]
        return None if any(x is None for x in values) else statistics.median(values)

    by_key = {(row["query"], row["tier"]): row for row in rows}
    for row in rows:
        row["median_s"] = statistics.median(row["seconds"])
        row["gpu_trace_s"] = median_of(row, "gpu_trace")
        row["host_f64_s"] = median_of(row, "host_f64")
        # A profile that names neither a GPU chunk nor host time, though the call took time.
        row["profile_empty"] = all(not p.get("chunks") and not p.get("host_f64") for p in row["profiles"])
        fast, ref = by_key[(row["query"], "fast")], by_key[(row["query"], "reference")]
        row["x_fast"] = (row["median_s"] / row["rays"]) / (fast["median_s"] / fast["rays"])
        row.update(accuracy(row["first"], ref["first"]))
        row["dtype"] = str(np.asarray(row["first"] if row["query"] == "transmittance" else row["first"].t).dtype)
    return {
        "rays": len(o32),
        "camera": [camera.width, camera.height],
        "rounds": rounds,
        "opacity": {"cut_outs": int(np.count_nonzero(opacity == 0)), "mean": float(opacity.mean()), "seed": 7},
        "skipped": [p for p in TIERS if p not in tiers],
        "rows": [{k: v for k, v in row.items() if k not in ("call", "first")} for row in rows],
    }


def accuracy(result, reference):
    """A tier's answer against the reference tier's: max |Δ|, rays over 1e-6, rays that differ.

    Transmittance: Δ of the light kept; "differ" bit for bit (None for float32, which always
    rounds). Hits: Δ of t where both name the same triangle; "differ": prim_id."""
    if isinstance(result, vkray.Hits):
        prim, ref_prim = result.prim_id.reshape(-1), reference.prim_id.reshape(-1)
        same = (prim == ref_prim) & (prim >= 0)
        delta = np.abs(result.t.reshape(-1)[same].astype(np.float64) - reference.t.reshape(-1)[same])
        differ = int(np.count_nonzero(prim != ref_prim))
        kept = float((prim >= 0).mean())
    else:
        value, ref_value = np.asarray(result).reshape(-1), np.asarray(reference).reshape(-1)
        delta = np.abs(value.astype(np.float64) - ref_value)
        differ = None if value.dtype != np.float64 else int(np.count_nonzero(value != ref_value))
        kept = float(value.mean())
    return {
        "max_delta": float(delta.max()) if len(delta) else 0.0,
        "over_1e6": int(np.count_nonzero(delta > 1e-6)),
        "differ": differ,
        "mean": kept,  # transmittance: the mean light kept; hits: the fraction of rays that hit
    }


def bench_big(device, scene, vertices, args):
    size = args.big_size
    camera = pinhole(vertices, size, size)
    scene.intersect(camera, outputs=["t"])  # warm-up
    seconds, profiles, hits = [], [], None
    for _ in range(args.big_repeat):
        start = time.perf_counter()
        hits = scene.intersect(camera, outputs=["t"])
        seconds.append(time.perf_counter() - start)
        profiles.append(device.last_trace_profile)
        print(f"  {device.backend}: big {size}x{size}: {seconds[-1]:.3f} s", file=sys.stderr, flush=True)
    traces = [p.get("gpu_trace") for p in profiles]
    trace = None if any(x is None for x in traces) else statistics.median(traces)
    return {
        "size": size,
        "rays": size * size,
        "seconds": seconds,
        "median_s": statistics.median(seconds),
        "gpu_trace_s": trace,
        "profiles": profiles,
        "hit_fraction": float(np.isfinite(hits.t).mean()),
        "explain": scene.explain("closest", ["t"], sensor=True),
    }


def load_average():
    """The 1-minute load average, or None where the platform has none."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def fmt(x, spec):
    return "-" if x is None else format(x, spec)


def print_backend(report):
    if report["rows"]:
        print_rows(report)
    if report["tiers"]:
        print_tiers(report)


def print_tiers(report):
    tiers = report["tiers"]
    width, height = tiers["camera"]
    print(f"### Tiers: transmittance and sensor rays, {report['device']}, backend {report['backend']}\n")
    print(
        f"Translucent bunny ({tiers['opacity']['cut_outs']:,} cut-outs, mean opacity {tiers['opacity']['mean']:.3f}). "
        f"transmittance: {tiers['rays']:,} rays from arrays (Δ: the light kept); intersect: outputs t, prim_id, "
        f"a {width}x{height} pinhole camera generated on the GPU (Δ: t where both name the same triangle; "
        f"≠: prim_id). Median of {tiers['rounds']} rounds after a warm-up call; × fast: wall time per ray over "
        "the fast tier's; accuracy against the reference tier."
        + (f" Skipped (no shaderFloat64): {', '.join(tiers['skipped'])}." if tiers["skipped"] else "")
        + "\n"
    )
    columns = ["query", "tier", "stages [ray-query branches]", "result", "rays", "mean", "median s", "Mrays/s"]
    columns += ["GPU trace s", "host f64 s", "× fast", "max \\|Δ\\|", "\\|Δ\\| > 1e-6", "≠ reference"]
    print(table_head(columns))
    for row in tiers["rows"]:
        stages, _ = shorten(row["explain"])
        median = f"{row['median_s']:.4f}" + (" (1 call)" if row["once"] else "")
        gpu, host = fmt(row["gpu_trace_s"], ".4f"), fmt(row["host_f64_s"], ".4f")
        if row["profile_empty"]:
            gpu = host = "n/r"
        print(
            f"| {row['query']} | {row['tier']} | {stages} | {row['dtype']} | {row['rays']:,} | {row['mean']:.4f} | "
            f"{median} | {row['rays'] / row['median_s'] / 1e6:.2f} | {gpu} | {host} | {row['x_fast']:.2f} | {row['max_delta']:.1e} | {row['over_1e6']:,} | "
            f"{fmt(row['differ'], ',')} |"
        )
    print(
        "\n(mean: the mean light kept (transmittance) or the fraction of pixels that hit (intersect). "
        "≠ of a float32 transmittance is left out: it differs from the f64 reference in every rounded bit. "
        "n/r: not reported: `Device.last_trace_profile` after the call names no GPU chunk and no host time.)\n"
    )


def print_rows(report):
    print(
        f"### {report['device']} ({report['device_type']}), backend `{report['backend']}`, driver {report['driver']}\n"
    )
    columns = ["effect", "query", "stages [ray-query branches]", "ray flags", "rays", "hit", "median s", "Mrays/s"]
    print(table_head(columns + ["GPU trace s", "× wall", "× GPU", "vs", "≠"]))
    for row in report["rows"]:
        stages, flags = shorten(row["explain"])
        print(
            f"| {row['name']} | {row['query']} | {stages} | {flags} | {row['rays']:,} | {row['hit_fraction']:.1%} | "
            f"{row['median_s']:.4f} | {row['rays'] / row['median_s'] / 1e6:.2f} | {fmt(row['gpu_trace_s'], '.4f')} | "
            f"{fmt(row['x_wall'], '.2f')} | {fmt(row['x_gpu'], '.2f')} | {row['vs'] or '-'} | "
            f"{fmt(row['differ'], ',')} |"
        )
    big = report["big"]
    if big:
        stages, flags = shorten(big["explain"])
        trace = big["gpu_trace_s"]
        print(
            f"\nDepth image {big['size']}x{big['size']} (outputs t) from a GPU-generated camera ({stages}; {flags}), "
            f"median of {len(big['seconds'])}, hit {big['hit_fraction']:.1%}:\n"
        )
        print("| rays | wall s | Grays/s end to end | GPU trace s | Grays/s trace alone |")
        print("|---|---|---|---|---|")
        print(
            f"| {big['rays']:,} | {big['median_s']:.4f} | {big['rays'] / big['median_s'] / 1e9:.3f} | "
            f"{fmt(trace, '.4f')} | {fmt(None if not trace else big['rays'] / trace / 1e9, '.3f')} |"
        )
    print()


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=float, default=200_000, help="rays per row (default 200,000)")
    parser.add_argument("--repeat", type=int, default=5, help="timed rounds after the warm-up (median; use at least 5)")
    parser.add_argument("--backend", choices=("ray_query", "pipeline"), help="default: every backend the device has")
    parser.add_argument("--device", default=None, help="index or name substring (default: vkray's choice)")
    parser.add_argument("--mesh", default="stanford-bunny", help="a shipped mesh's name or an OBJ file (default: the bunny)")
    parser.add_argument("--big", action="store_true", help="add the 4096x4096 depth image from a GPU camera")
    parser.add_argument("--big-size", type=int, default=4096, help="side of --big's image")
    parser.add_argument("--big-repeat", type=int, default=5)
    parser.add_argument("--tiers", action="store_true", help="add the precision tiers of transmittance and sensor rays")
    parser.add_argument("--tiers-only", action="store_true", help="the tier table alone (implies --tiers)")
    parser.add_argument("--tier-rays", type=float, default=100_000, help="rays for --tiers (default 100,000)")
    parser.add_argument(
        "--slow-reference",
        type=float,
        default=20.0,
        help="a reference call slower than this (seconds) is timed once, by its warm-up (default 20)",
    )
    parser.add_argument("--json", type=pathlib.Path)
    args = parser.parse_args()
    if args.repeat < 1 or args.big_repeat < 1:
        parser.error("--repeat and --big-repeat must be at least 1")
    if args.tiers_only and args.big:
        parser.error("--big belongs to the main rows, which --tiers-only leaves out")
    tiers = args.tiers or args.tiers_only

    vertices, faces = load_mesh(args.mesh)
    n = int(args.rays)
    side, o32, d32 = make_rays(vertices, n)
    rays = None if args.tiers_only else (o32, d32)
    tier_rays = make_rays(vertices, int(args.tier_rays))[1:] if tiers else None

    info = vkray.Device(args.device).info
    if args.backend:
        backends = [args.backend]
    else:
        backends = [b for b, has in (("ray_query", info.ray_query), ("pipeline", info.ray_tracing_pipeline)) if has]

    host = f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}"
    load_before = load_average()
    reports = []
    for backend in backends:
        reports.append(bench_backend(backend, args, vertices, faces, rays, tier_rays))
    load_after = load_average()

    print(f"Command: `python {' '.join(sys.argv)}`\n")
    if args.tiers_only:
        print(
            f"Mesh {pathlib.Path(args.mesh).name}: {len(faces):,} triangles. Host: {host}; vkray {vkray.__version__}, "
            f"numpy {np.__version__}. Load average (1 min) before the run {fmt(load_before, '.2f')}, after "
            f"{fmt(load_after, '.2f')} (this run's own included).\n"
        )
    else:
        print_header(args, faces, o32, side, host, load_before, load_after)
    for report in reports:
        print_backend(report)
    if args.json:
        payload = {"argv": sys.argv, "host": host, "mesh": str(args.mesh), "triangles": len(faces)}
        payload["rays"] = None if args.tiers_only else len(o32)
        payload["tier_rays"] = len(tier_rays[0]) if tiers else None
        payload["load_average"] = {"before": load_before, "after": load_after}
        payload["backends"] = reports
        args.json.write_text(json.dumps(payload, indent=1, default=str))


def make_rays(vertices, n):
    """(camera side, origins, directions) float32: half camera_rays, half random_rays (seed 11)."""
    side = max(1, int(round(math.sqrt(n / 2))))
    origin, cam = oracle_camera_rays(vertices, side, side, FORWARD)
    ro, rd = random_rays(vertices, n - side * side, seed=11)
    o32 = np.ascontiguousarray(np.concatenate([np.broadcast_to(origin, cam.shape), ro]), dtype=np.float32)
    d32 = np.ascontiguousarray(np.concatenate([cam, rd]), dtype=np.float32)
    return side, o32, d32


def print_header(args, faces, o32, side, host, load_before, load_after):
    print(
        f"Mesh {pathlib.Path(args.mesh).name}: {len(faces):,} triangles. Rays: {len(o32):,} ({side * side:,} camera, "
        f"{len(o32) - side * side:,} random), float32, uploaded each call (but the GPU camera row). "
        f"Host: {host}; vkray {vkray.__version__}, numpy {np.__version__}. Median of {args.repeat} rounds after "
        "one warm-up call; × = time per ray over the vs row's (wall clock; GPU trace alone); "
        "≠ = rays answering differently from the vs row. "
        f"Load average (1 min) before the run {fmt(load_before, '.2f')}, after {fmt(load_after, '.2f')} (this run's "
        "own included): on a CPU device, other processes' load shows in every time.\n"
    )


if __name__ == "__main__":
    main()
