"""examples/tour.ipynb runs top to bottom in a fresh kernel (nbclient, which scripts/setup.sh
installs: requirements-dev.txt) without an error, under the validation layer where the suite has
it, and shows what it is there to show: the summaries as HTML, the pictures as PNGs."""

import base64
import pathlib

import nbclient
import nbformat

from conftest import VALIDATION

NOTEBOOK = pathlib.Path(__file__).resolve().parents[1] / "examples" / "tour.ipynb"


def test_tour_runs_and_shows_its_pictures(monkeypatch):
    if VALIDATION:
        monkeypatch.setenv("VKRAY_VALIDATION", "1")
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    assert not any(cell.get("outputs") for cell in notebook.cells), "commit the notebook without outputs"
    client = nbclient.NotebookClient(
        notebook, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOK.parent)}}
    )
    client.execute()  # raises CellExecutionError, naming the cell, if any cell fails

    outputs = [output for cell in notebook.cells if cell.cell_type == "code" for output in cell.outputs]
    assert not [output for output in outputs if output.output_type == "error"]
    pngs = [base64.b64decode(output.data["image/png"]) for output in outputs if "image/png" in output.get("data", {})]
    # hits (their _repr_png_), hits.show("normal"), hits.show("instance_id"), a GPU camera's depth,
    # two previews.
    assert len(pngs) == 6 and all(png.startswith(b"\x89PNG\r\n\x1a\n") for png in pngs)
    html = [output.data["text/html"] for output in outputs if "text/html" in output.get("data", {})]
    assert len(html) == 3  # the device, the mesh, the scene
    assert "vkray.Device" in html[0] and "5,856" in html[1] and "11,712" in html[2]
    text = "".join(output.get("text", "") for output in outputs if output.output_type == "stream")
    for tier in ("fast", "refined", "reference"):
        assert f"{tier:>9}  " in text
    # The veil's translucent triangles get the any-hit stage or branch; the opaque scene does not.
    assert "lidar points:" in text and "light kept: mean" in text
