"""Draws docs/pipeline.png, the picture of cosy's pipeline in the README.

Run once after changing it: python docs/pipeline_figure.py (matplotlib only).
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

OUT = Path(__file__).resolve().parent / "pipeline.png"

# (x, title, command, what it writes)
STAGES = [
    (0.0, "BOP dataset", "images, camera.json,\nmeshes (mm)", "your photos: made\nby cosy new-dataset"),
    (1.0, "detect", "2D boxes per image", "detections.json"),
    (2.0, "estimate", "one pose per box,\neach view alone\n(CosyPose stage 1)", "candidates.csv\nT_cam_obj"),
    (3.0, "match", "one object across\nviews, relative\ncameras (stage 2)", "match/\ngroups.json ..."),
    (4.0, "refine", "cameras + objects\nadjusted together\n(stage 3)", "refine/\npredictions.csv\nscene.json"),
    (5.0, "evaluate\n+ viz", "BOP19 AR, AUC ADD-S;\nfigures, report", "evaluate/\nreport.html"),
]


def main() -> None:
    fig, ax = plt.subplots(figsize=(11, 3.4), dpi=110)
    ax.set_xlim(-0.5, 5.5)
    ax.set_ylim(-1.3, 1.25)
    ax.axis("off")
    w, h = 0.82, 1.35
    for i, (x, title, what, writes) in enumerate(STAGES):
        colour = "#e8eef7" if 0 < i < 5 else "#eeeeee"
        ax.add_patch(FancyBboxPatch((x - w / 2, -h / 2 + 0.25), w, h, boxstyle="round,pad=0.02",
                                    fc=colour, ec="#35506b", lw=1.2))
        ax.text(x, 0.72, title if i in (0, 5) else f"cosy {title}", ha="center", va="center",
                fontsize=10.5, weight="bold", color="#1d2f40")
        ax.text(x, 0.12, what, ha="center", va="center", fontsize=8.3, color="#222222")
        ax.text(x, -0.78, writes, ha="center", va="center", fontsize=8, family="monospace",
                color="#5a3d00")
        if i < len(STAGES) - 1:
            ax.add_patch(FancyArrowPatch((x + w / 2, 0.25), (x + 1 - w / 2, 0.25),
                                         arrowstyle="-|>", mutation_scale=14, lw=1.4, color="#35506b"))
    ax.text(2.5, 1.12, "cosy run: every stage per scene, cached and resumable, in one run folder",
            ha="center", va="center", fontsize=9.5, style="italic", color="#35506b")
    ax.annotate("", xy=(4.6, 1.0), xytext=(0.4, 1.0),
                arrowprops=dict(arrowstyle="-", color="#35506b", lw=0.8, ls="--"))
    ax.text(-0.5, -1.22, "bottom row: the files each stage writes (BOP formats, lengths in millimetres)", fontsize=7.5,
            color="#5a3d00", ha="left")
    fig.tight_layout(pad=0.2)
    fig.savefig(OUT)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
