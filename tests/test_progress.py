"""progress=True on queries: the core reports (done, total) between chunks, in order, up to the
total; a progress bar (tqdm's, or a line on stderr) shows it; an exception from the callback stops
the query as Ctrl-C does."""

import numpy as np
import pytest

import vkray
from vkray import _progress


def _scene_and_rays(device, n=5000):
    scene = device.scene(device.mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]))
    o = np.random.default_rng(0).uniform(0.0, 0.3, (n, 3))
    o[:, 2] = 1.0
    return scene, o, np.tile([0.0, 0.0, -1.0], (n, 1))


@pytest.fixture
def small_chunks(any_device):
    previous = any_device.chunk_rays
    any_device.chunk_rays = 1000
    yield any_device
    any_device.chunk_rays = previous


@pytest.mark.parametrize("query", ["trace", "trace_all", "count", "contains", "reference"])
def test_reports_are_in_order_and_reach_the_total(small_chunks, query):
    scene, o, d = _scene_and_rays(small_chunks)
    calls = []
    core = scene._core
    report = lambda done, total: calls.append((done, total))  # noqa: E731
    if query == "trace":
        core.trace(o, d, 0.0, np.inf, "closest", ["t"], "fast", None, None, progress=report)
    elif query == "trace_all":
        core.trace_all(o, d, 0.0, np.inf, ["t"], "fast", None, None, None, progress=report)
    elif query == "count":
        core.count(o, d, 0.0, np.inf, "fast", None, None, progress=report)
    elif query == "contains":
        core.contains(o, "reference", True, report)
    else:
        core.trace(o, d, 0.0, np.inf, "closest", ["t"], "reference", None, None, progress=report)
    assert calls and all(total == len(o) for _, total in calls)
    # One pass or two (all hits: counting, then storing): each rises to the total.
    passes = np.split(np.array([done for done, _ in calls]), np.nonzero(np.diff([c[0] for c in calls]) < 0)[0] + 1)
    assert len(passes) <= 2
    for done in passes:
        assert (np.diff(done) > 0).all() and done[-1] == len(o)


def test_an_exception_from_the_callback_stops_the_query(small_chunks):
    scene, o, d = _scene_and_rays(small_chunks)

    def stop(done, total):
        raise KeyError("stop here")

    with pytest.raises(KeyError, match="stop here"):
        scene._core.count(o, d, 0.0, np.inf, "fast", None, None, progress=stop)
    # The device still answers.
    assert scene.count(o, d).sum() == len(o)


def test_progress_true_draws_a_bar(small_chunks, capsys, monkeypatch):
    scene, o, d = _scene_and_rays(small_chunks)
    monkeypatch.setattr(_progress.importlib, "import_module", _no_module)
    hits = scene.intersect(o, d, progress=True)
    assert hits.hit.all()
    assert "vkray intersect: 5000/5000" in capsys.readouterr().err
    for query in (scene.occluded, scene.intersect_all, scene.count):
        query(o, d, progress=True)
    assert scene.contains(o, precision="reference", method="winding", progress=True).shape == (len(o),)
    err = capsys.readouterr().err
    for what in ("occluded", "intersect_all", "count", "contains"):
        assert f"vkray {what}: 5000/5000" in err, what


def test_a_bar_stopped_part_way_ends_its_line(capsys, monkeypatch):
    monkeypatch.setattr(_progress.importlib, "import_module", _no_module)
    bar = _progress.Progress("count")
    bar(1500, 3001)
    bar.close()
    assert capsys.readouterr().err == "\rvkray count: 1500/3001\n"
    bar = _progress.Progress("count")
    bar(3001, 3001)
    bar.close()  # done: the line is ended already
    assert capsys.readouterr().err == "\rvkray count: 3001/3001\n"


def test_progress_true_uses_tqdm(small_chunks, monkeypatch):
    scene, o, d = _scene_and_rays(small_chunks)
    bars = []

    class FakeBar:
        def __init__(self, total, **kwargs):
            self.total, self.n, self.closed, self.kwargs = total, 0, False, kwargs
            bars.append(self)

        def reset(self, total):
            self.total, self.n = total, 0

        def refresh(self):
            pass

        def close(self):
            self.closed = True

    class FakeModule:
        tqdm = FakeBar

    monkeypatch.setattr(_progress.importlib, "import_module", lambda name: FakeModule)
    scene.intersect_all(o, d, progress=True)
    assert len(bars) == 1 and bars[0].n == len(o) and bars[0].closed
    assert "intersect_all" in bars[0].kwargs["desc"]


def test_meshes_report_each_batch(any_device):
    """Device.meshes: (built, total) after each batch of the scratch budget."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    items = [(v + k, np.array([[0, 1, 2]])) for k in range(6)]
    calls = []
    budget = 2 * int(any_device.meshes(items[:1])[0].stats["scratch_bytes"])  # two meshes a batch
    cores = any_device._core.meshes([(m[0], m[1].astype(np.int32)) for m in items], "fast_trace", False, False,
                                    budget, "float32", lambda done, total: calls.append((done, total)))
    assert len(cores) == 6
    assert calls[-1] == (6, 6) and len(calls) >= 3
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)
    assert len(any_device.meshes(items, progress=True)) == 6


def _no_module(name):
    raise ImportError(name)


def test_no_progress_by_default(any_device, capsys):
    scene, o, d = _scene_and_rays(any_device, 100)
    scene.intersect(o, d)
    assert capsys.readouterr().err == ""
    assert isinstance(vkray.Device, type)
