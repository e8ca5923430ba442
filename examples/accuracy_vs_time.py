"""What accuracy costs in time: every precision tier, on every backend the device offers, against
the f64 reference, with Embree (embreex, robust mode) measured the same way as a baseline.

    python examples/accuracy_vs_time.py              # writes accuracy.md and accuracy.png here
    python examples/accuracy_vs_time.py --out docs   # updates the project's docs/accuracy.md

The measured table replaces what lies between the `<!-- SECTION -->` and `<!-- /SECTION -->`
lines of accuracy.md (`--section`, default `measured`; the file is made if missing), so the
prose around it stays and several devices can each have their block.

Two workloads, at offsets 0, 1e3, 1e5 and 1e7 (added to every coordinate, baked into float64
vertices):
- edges: rays through the vertices and edge midpoints that triangles of a random heightfield share.
  Each ray must report exactly one triangle. Misses and double counts are counted by tracing the
  rays against 18 scenes, each holding triangles that share no vertex (a ray reported by two
  triangles hits two scenes).
- bunny: random rays through the Stanford bunny's bounding box; time per ray, and how often the
  tier picks another triangle than the reference.
|Δt| is measured against the "reference" tier, relative to the geometry's size (heightfield cell,
bunny's bounding-box diagonal): the error a user sees in hit positions, as a fraction of the model.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import vkray  # noqa: E402
from oracle import heightfield, load_mesh, random_rays, rays_through, shared_targets  # noqa: E402

OFFSETS = (0.0, 1e3, 1e5, 1e7)
COLORS = 18


def best_time(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def embree_scene(vertices, faces):
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene(robust=True)
    TriangleMesh(scene, np.ascontiguousarray(vertices[faces], dtype=np.float32))
    return scene


def embree_t(scene, origins, directions):
    """Embree's t (float64, inf on a miss) and prim; Embree takes float32 rays only."""
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    result = scene.run(o, d, output=1)
    prim = result["primID"].astype(np.int64)
    t = np.where(prim >= 0, result["tfar"].astype(np.float64), np.inf)
    return t, prim


class Tracers:
    """The tiers of one device backend, and Embree, behind one call."""

    def __init__(self, device):
        self.device = device
        probe = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
        self.tiers = []
        for tier in vkray.PRECISIONS:
            try:
                probe.intersect([0.2, 0.2, 1.0], [0, 0, -1], precision=tier)
                self.tiers.append(tier)
            except vkray.UnsupportedError as e:
                print(f"# {device.backend}: {tier} unavailable: {e}", file=sys.stderr)


def percentiles(errors):
    errors = errors[np.isfinite(errors)]
    if errors.size == 0:
        return (np.nan, np.nan, np.nan)
    return tuple(float(x) for x in np.percentile(errors, [50, 99, 100]))


def edges_workload(tracers, rows, n, offset):
    v, f, color = heightfield(n, seed=3, offset=offset)
    targets = shared_targets(v, f, n)
    origins, directions = rays_through(targets, seed=4)
    length = np.linalg.norm(directions, axis=1)
    device = tracers.device
    parts = [device.scene(device.mesh(v, f[color == c])) for c in range(COLORS)]
    whole = device.scene(device.mesh(v, f))
    ref_t = whole.intersect(origins, directions, precision="reference", outputs=["t"]).t

    def record(name, counts, t, seconds):
        dt = np.abs(t - ref_t) * length  # in heightfield cells (unit squares)
        rows.append(dict(backend=device.backend, tier=name, workload="edges", offset=offset, rays=len(targets),
                         ns=1e9 * seconds / len(targets), misses=int(np.sum(counts == 0)),
                         doubles=int(np.sum(counts > 1)), dt=percentiles(dt), other_prim=np.nan))

    for tier in tracers.tiers:
        counts = np.zeros(len(targets), int)
        for part in parts:
            t = part.intersect(origins, directions, precision=tier, outputs=["t"]).t
            counts += np.abs(t - 1.0) * length < 1e-3
        t = whole.intersect(origins, directions, precision=tier, outputs=["t"]).t.astype(np.float64)
        seconds = best_time(lambda: whole.intersect(origins, directions, precision=tier, outputs=["t"]))
        record(tier, counts, t, seconds)
    if device.backend == tracers.first_backend:
        counts = np.zeros(len(targets), int)
        for c in range(COLORS):
            t, _ = embree_t(embree_scene(v, f[color == c]), origins, directions)
            counts += np.abs(t - 1.0) * length < 1e-3
        scene = embree_scene(v, f)
        t, _ = embree_t(scene, origins, directions)
        record("embree (f32, robust)", counts, t, best_time(lambda: embree_t(scene, origins, directions)))


def bunny_workload(tracers, rows, rays, offset):
    v, f = load_mesh("stanford-bunny")
    v = v + offset
    size = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    origins, directions = random_rays(v, rays, seed=11)
    length = np.linalg.norm(directions, axis=1)
    device = tracers.device
    scene = device.scene(device.mesh(v, f))
    ref = scene.intersect(origins, directions, precision="reference", outputs=["t", "prim_id"])

    def record(name, t, prim, seconds):
        both = np.isfinite(t) & ref.hit
        dt = np.abs(t[both] - ref.t[both]) * length[both] / size
        rows.append(dict(backend=device.backend, tier=name, workload="bunny", offset=offset, rays=rays,
                         ns=1e9 * seconds / rays, misses=int(np.sum(ref.hit & ~np.isfinite(t))),
                         doubles=int(np.sum(~ref.hit & np.isfinite(t))), dt=percentiles(dt),
                         other_prim=float(np.mean(prim[ref.hit] != ref.prim_id[ref.hit]))))

    for tier in tracers.tiers:
        hits = scene.intersect(origins, directions, precision=tier, outputs=["t", "prim_id"])
        seconds = best_time(lambda: scene.intersect(origins, directions, precision=tier, outputs=["t", "prim_id"]))
        record(tier, hits.t.astype(np.float64), hits.prim_id, seconds)
    if device.backend == tracers.first_backend:
        em = embree_scene(v, f)
        t, prim = embree_t(em, origins, directions)
        record("embree (f32, robust)", t, prim, best_time(lambda: embree_t(em, origins, directions)))


def write_table(rows):
    lines = [
        "| workload | offset | backend | tier | ns/ray | misses | double counts (edges), false hits (bunny) | p50 \\|Δt\\| | p99 \\|Δt\\| | max \\|Δt\\| | other triangle |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        other = "" if np.isnan(r["other_prim"]) else f"{r['other_prim']:.4%}"
        p50, p99, top = (f"{x:.1e}" for x in r["dt"])
        lines.append(f"| {r['workload']} | {r['offset']:g} | {r['backend'] if 'embree' not in r['tier'] else '—'} | "
                     f"{r['tier']} | {r['ns']:.1f} | {r['misses']} | {r['doubles']} | {p50} | {p99} | {top} | {other} |")
    return "\n".join(lines)


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    markers = {"fast": "o", "refined": "s", "exact": "D", "reference": "^"}
    for ax, workload in zip(axes, ("bunny", "edges")):
        for r in rows:
            if r["workload"] != workload:
                continue
            floor = 1e-17  # exact zeros on a log axis
            y = max(r["dt"][1], floor) if np.isfinite(r["dt"][1]) else np.nan
            embree = "embree" in r["tier"]
            ax.scatter(r["ns"], y, marker="x" if embree else markers[r["tier"]], s=50,
                       color=plt.cm.viridis(OFFSETS.index(r["offset"]) / (len(OFFSETS) - 1)),
                       edgecolor="black" if r["backend"] == "pipeline" and not embree else None)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time per ray (ns, log)")
        ax.set_ylabel("p99 |Δt| / model size (log; 1e-17 = exact)")
        ax.set_title(f"{workload}: accuracy against time")
        ax.grid(True, which="major", alpha=0.3)
    handles = [plt.Line2D([], [], marker=m, linestyle="", color="gray", label=t) for t, m in markers.items()]
    handles.append(plt.Line2D([], [], marker="x", linestyle="", color="gray", label="embree f32 robust"))
    handles += [plt.Line2D([], [], marker="o", linestyle="", color=plt.cm.viridis(i / (len(OFFSETS) - 1)),
                           label=f"offset {o:g}") for i, o in enumerate(OFFSETS)]
    axes[1].legend(handles=handles, fontsize=8, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rays", type=int, default=100_000, help="random rays through the bunny")
    parser.add_argument("--grid", type=int, default=24, help="heightfield vertices per side")
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("."), help="the folder for accuracy.md and its picture")
    parser.add_argument("--section", default="measured", help="which marked block of accuracy.md to replace")
    args = parser.parse_args()

    info = vkray.devices()[0]
    backends = [b for b, ok in (("ray_query", info.ray_query), ("pipeline", info.ray_tracing_pipeline)) if ok]
    rows = []
    for backend in backends:
        tracers = Tracers(vkray.Device(backend=backend))
        tracers.first_backend = backends[0]
        for offset in OFFSETS:
            edges_workload(tracers, rows, args.grid, offset)
            bunny_workload(tracers, rows, args.rays, offset)
    rows.sort(key=lambda r: (r["workload"], r["offset"], "embree" in r["tier"], r["backend"], vkray.PRECISIONS.index(r["tier"]) if r["tier"] in vkray.PRECISIONS else 9))
    args.out.mkdir(parents=True, exist_ok=True)
    plot(rows, args.out / ("accuracy.png" if args.section == "measured" else f"accuracy-{args.section}.png"))
    table = write_table(rows)
    command = "python examples/accuracy_vs_time.py" + "".join(f" {a}" for a in sys.argv[1:])
    device = vkray.Device()
    measured = (f"Command: `{command}`\n\nDevice: {device.name} ({device.info.device_type}), driver "
                f"{device.info.driver}; Embree (embreex) on one core.\n\n{table}\n")
    doc = args.out / "accuracy.md"
    start, end = f"<!-- {args.section} -->\n", f"<!-- /{args.section} -->"
    text = doc.read_text() if doc.exists() else "# Accuracy and its cost\n\n"
    if start not in text:
        text += f"\n{start}{end}\n"
    head, rest = text.split(start, 1)
    tail = rest.split(end, 1)[1]
    doc.write_text(f"{head}{start}{measured}{end}{tail}")
    print(measured)


if __name__ == "__main__":
    main()
