"""A hostile-input harness (issue 34): generated cases, run in child processes with a timeout,
sorted into crashes (the process died or raised something other than a clean error),
hangs (past the timeout), wrong answers (disagreeing with brute force or the reference tier) and
the rest (right answers, clean refusals). 0 crashes, 0 hangs and 0 wrong answers are required.
Bounded: the cases run in batches, each batch in its own child process with a timeout; a case a
child did not answer runs again alone, so a crash or a hang is laid at its own case."""

import json
import subprocess
import sys
import textwrap

import numpy as np

# One case: its seed picks a mesh, a query kind, a tier and an offset; the child prints one JSON
# verdict: "right", "refused" (a documented error type with a message), or "wrong" with details.
CHILD = textwrap.dedent(
    r"""
    import json, sys
    import numpy as np
    sys.path.insert(0, "tests")
    import vkray
    from test_hostile import _brute_distance, _has_slivers
    device = vkray.Device()


    def judge(seed, kind, tier, offset):
        rng = np.random.default_rng(seed)
        v = rng.uniform(-1, 1, (30, 3))
        f = rng.integers(0, 30, (12, 3))
        f[0] = [f[0, 0], f[0, 0], f[0, 1]]  # a repeated corner
        f[1] = f[2]  # a duplicate
        hostile = rng.choice([np.nan, np.inf, -np.inf, 1e300, -1e39, 0.0])
        verdict = {"seed": seed, "kind": kind, "tier": tier, "offset": offset}
        try:
            scene = device.scene(device.mesh(v, f))
            n = 8
            d = rng.normal(size=(n, 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            p = rng.uniform(-1, 1, (n, 3)) + d * offset
            if rng.random() < 0.3:
                p[rng.integers(0, n)] = hostile
            if kind == "distance":
                got = scene.distance(p, precision=tier)
                want = _brute_distance(v, f, p)
                rtol = 1e-5 if tier == "fast" else 1e-9
                ok = _has_slivers(v, f) or np.allclose(got, want, rtol=rtol, atol=1e-12)
                verdict["result"] = "right" if ok else "wrong"
                verdict["detail"] = [got.tolist(), want.tolist()]
            elif kind == "count":
                o = p - d * 4.0
                got = scene.count(o, d, precision=tier)
                want = scene.count(o, d, precision="reference")
                verdict["result"] = "right" if (tier == "fast" or (got == want).all()) else "wrong"
                verdict["detail"] = [got.tolist(), want.tolist()]
            else:  # closest points vs the reference tier
                got = scene.closest_points(p, precision=tier)
                want = scene.closest_points(p, precision="reference")
                same = np.allclose(got.distance, want.distance, rtol=1e-5 if tier == "fast" else 0.0, atol=0.0)
                verdict["result"] = "right" if same and got.hit.all() else "wrong"
                verdict["detail"] = [got.distance.tolist(), want.distance.tolist()]
        except (ValueError, TypeError, MemoryError, vkray.UnsupportedError) as e:
            verdict["result"] = "refused"
            verdict["detail"] = f"{type(e).__name__}: {e}"[:300]
        return verdict


    for seed, kind, tier, offset in json.loads(sys.argv[1]):
        print("VERDICT " + json.dumps(judge(seed, kind, tier, offset)), flush=True)
    """
)

KINDS = ("distance", "count", "closest")
TIERS = ("fast", "exact", "reference")
OFFSETS = (0.0, 1e-30, 1e8, 1e20, 1e38, 1e155, 1e300)


def _cases(n: int):
    rng = np.random.default_rng(34)
    for seed in range(n):
        yield seed, KINDS[seed % 3], TIERS[(seed // 3) % 3], float(OFFSETS[int(rng.integers(0, len(OFFSETS)))])


def _run_batch(batch, timeout: float):
    """The batch's verdicts, from one child. Where the child died or hung (even after answering
    every case, as in its teardown), each case runs again alone, so that a crash or a hang is
    laid at its own case, and the batch's failure is reported too: one that no case repeats alone
    (caused by an earlier case's leftovers) still fails the run."""
    try:
        done = subprocess.run(
            [sys.executable, "-c", CHILD, json.dumps(batch)],
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        stdout, stderr, returncode = done.stdout, done.stderr, done.returncode
    except subprocess.TimeoutExpired as timed_out:
        stdout, stderr, returncode = _text(timed_out.stdout), _text(timed_out.stderr), None
    verdicts = [json.loads(line[len("VERDICT ") :]) for line in stdout.splitlines() if line.startswith("VERDICT ")]
    if returncode == 0 and len(verdicts) == len(batch):
        return verdicts
    failed = {
        "case": batch[0] if len(batch) == 1 else batch,
        "result": "hang" if returncode is None else "crash",
        "detail": (stderr or "")[-1500:],
    }
    if len(batch) == 1:
        return [failed]
    return [v for case in batch for v in _run_batch([case], timeout)] + [failed]


def _text(captured) -> str:
    return captured.decode(errors="replace") if isinstance(captured, bytes) else (captured or "")


def test_generated_hostile_cases_neither_crash_hang_nor_answer_wrong():
    from concurrent.futures import ThreadPoolExecutor

    cases = list(_cases(96))
    batches = [cases[i : i + 8] for i in range(0, len(cases), 8)]  # a child's start-up costs ~1 s
    with ThreadPoolExecutor(max_workers=2) as pool:
        verdicts = [v for batch in pool.map(lambda b: _run_batch(b, timeout=60.0), batches) for v in batch]
    assert len(verdicts) >= len(cases)  # a verdict a case, and one a failed batch
    tally = {}
    for v in verdicts:
        tally[v["result"]] = tally.get(v["result"], 0) + 1
    bad = [v for v in verdicts if v["result"] in ("crash", "hang", "wrong")]
    assert not bad, f"{tally}: " + json.dumps(bad[:5], default=str)[:4000]
    # The harness must have exercised both answers and refusals.
    assert tally.get("right", 0) > 0 and tally.get("refused", 0) > 0, tally
