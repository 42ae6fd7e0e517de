"""report.html opened in a real headless browser (Chromium): the page renders with every image.

Skipped when no ``chromium`` (Debian's package) or ``chromium-browser`` is on PATH."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from cosy_cli import viz

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on PATH (Debian: apt-get install chromium)")

FIG_RGB = (230, 0, 200)  # magenta: the group figures
PLOT_RGB = (0, 190, 210)  # cyan: the evaluation plots

# Run after the page's load event: every <img> made eager (the figures are lazy-loaded), then
# once all have settled, their sources and natural widths are written into <pre id="imgcheck">.
CHECK_JS = """
<script>
for (const im of document.images) { im.loading = "eager"; }
window.addEventListener("load", () => {
  Promise.all([...document.images].map(im => (im.complete ? null : new Promise(r => { im.onload = im.onerror = r; }))))
    .then(() => {
      const pre = document.createElement("pre");
      pre.id = "imgcheck";
      pre.textContent = JSON.stringify([...document.images].map(im => [im.getAttribute("src"), im.naturalWidth]));
      document.body.appendChild(pre);
    });
});
</script>
"""


def chromium(args: list[str], profile: Path) -> str:
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--disable-extensions", "--hide-scrollbars", f"--user-data-dir={profile}", *args]
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail(f"chromium did not finish within 120 s: {' '.join(cmd)}")
    assert res.returncode == 0, f"chromium failed ({res.returncode}): {res.stderr[-2000:]}"
    return res.stdout


def loaded_images(html: Path, profile: Path) -> list[tuple[str, int]]:
    """[(src, naturalWidth)] of every <img> of ``html`` once the browser has loaded the page."""
    probe = html.with_name(html.stem + ".probe.html")
    probe.write_text(html.read_text().replace("</body>", CHECK_JS + "</body>"))
    dom = chromium(["--virtual-time-budget=20000", "--dump-dom", probe.as_uri()], profile)
    m = re.search(r'<pre id="imgcheck">(.*?)</pre>', dom, re.S)
    assert m, "the probe script did not report (page not loaded?)"
    import html as h

    return [tuple(x) for x in json.loads(h.unescape(m.group(1)))]


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> Path:
    """A run folder's report.html with two group figures and two evaluation plots (plain PNGs of a
    known colour), written by viz.write_report."""
    from PIL import Image

    R = tmp_path_factory.mktemp("run")
    (R / "run.json").write_text(json.dumps({"format": "cosy-run", "dataset": "data_samples", "split": "test",
                                            "scene_ids": [1, 2], "stages": {"match": {"status": "done",
                                                                                      "time_s": 0.5}}}))
    figs = []
    for s in (1, 2):
        p = R / "figures" / viz.figure_name(s, 0)
        p.parent.mkdir(exist_ok=True)
        img = np.zeros((300, 900, 3), dtype=np.uint8)
        img[:] = FIG_RGB
        img[::20] = 255
        Image.fromarray(img).save(p)
        figs.append(p)
    for sub in ("single_view", "multi_view"):
        d = R / "evaluate" / sub
        d.mkdir(parents=True)
        (d / "scores.json").write_text(json.dumps({"auc_adds": 0.9, "recall_adds_0.1d": 0.8}))
        img = np.zeros((200, 500, 3), dtype=np.uint8)
        img[:] = PLOT_RGB
        Image.fromarray(img).save(d / "report.png")
    return viz.write_report(R, figs, captions={str(f): f"caption of {f.stem}" for f in figs})


def test_report_renders_with_its_images(report, tmp_path):
    imgs = loaded_images(report, tmp_path / "profile")
    srcs = sorted(s for s, _ in imgs)
    assert srcs == ["evaluate/multi_view/report.png", "evaluate/single_view/report.png",
                    "figures/scene_000001_group_000.png", "figures/scene_000002_group_000.png"]
    assert all(w > 0 for _, w in imgs), imgs

    # the page as a reader sees it: text and both kinds of images drawn
    shot = tmp_path / "report.png"
    chromium([f"--screenshot={shot}", "--window-size=1280,2400", "--virtual-time-budget=20000", report.as_uri()],
             tmp_path / "profile2")
    from PIL import Image

    px = np.asarray(Image.open(shot).convert("RGB")).reshape(-1, 3).astype(int)
    near = lambda rgb: (np.abs(px - rgb).max(1) < 30).mean()  # noqa: E731
    assert near((255, 255, 255)) < 0.97, "blank page"
    assert (px.max(1) < 80).mean() > 0.002, "no text"
    assert near(FIG_RGB) > 0.02, "the figures are not drawn"
    assert near(PLOT_RGB) > 0.01, "the evaluation plots are not drawn"


def test_a_broken_image_link_is_caught(report, tmp_path):
    """The probe is not blind: a report whose figure link points nowhere reports that image unloaded."""
    broken = report.with_name("broken.html")
    broken.write_text(report.read_text().replace('src="figures/scene_000002_group_000.png"',
                                                 'src="figures/missing.png"'))
    imgs = dict(loaded_images(broken, tmp_path / "profile"))
    assert imgs["figures/missing.png"] == 0
    assert imgs["figures/scene_000001_group_000.png"] > 0
