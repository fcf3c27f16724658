"""Pictures for docs/: the methods side by side on one phantom, and spheroseg
on the real CETUS Patient 7 volumes.

    python benchmarks/figures.py

Writes docs/comparison.png and docs/cetus_patient7.png.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import DOCS, PEER_PARAMS, run_sitk, run_skimage  # noqa: E402

from spheroseg.surfaces.metrics import dice  # noqa: E402
from spheroseg.synthetic.phantom import FAMILIES, make_phantom  # noqa: E402
from spheroseg.tracking.segment import segment  # noqa: E402
from spheroseg.volumes.volume import Volume  # noqa: E402

CETUS = Path(__file__).resolve().parents[2] / "shared" / "data" / "cetus"


def _views(volume, centre):
    k, j, i = np.round(volume.world_to_index(centre)[::-1]).astype(int)
    return [(lambda a, j=j: a[:, j]), (lambda a, i=i: a[:, :, i]), (lambda a, k=k: a[k])]


def comparison():
    ph = make_phantom(seed=0, **FAMILIES["dropout"])
    masks = {"truth": ph.truth_mask}
    masks["spheroseg (local)"] = segment(ph.volume, ph.apex, ph.base).mask(ph.volume)
    masks["scikit-image morph. Chan-Vese"] = run_skimage(ph.volume, ph.apex, ph.base, **PEER_PARAMS["skimage"])[0]
    masks["SimpleITK Chan-Vese"] = run_sitk(ph.volume, ph.apex, ph.base, **PEER_PARAMS["sitk"])[0]
    colours = {"truth": "red", "spheroseg (local)": "yellow", "scikit-image morph. Chan-Vese": "cyan",
               "SimpleITK Chan-Vese": "magenta"}
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.5))
    views = _views(ph.volume, (ph.apex + ph.base) / 2)
    for ax, view in zip(axes, views):
        ax.imshow(view(ph.volume.array), cmap="gray", interpolation="nearest")
        for name, m in masks.items():
            if view(m).any():
                ax.contour(view(m), [0.5], colors=colours[name], linewidths=1.2 if name == "truth" else 1.0)
        ax.set_xticks([])
        ax.set_yticks([])
    handles = [plt.Line2D([], [], color=colours[n], label=f"{n}" + ("" if n == "truth" else f" (Dice {dice(m, ph.truth_mask):.3f})"))
               for n, m in masks.items()]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=9)
    fig.suptitle("Phantom 'dropout', seed 0: long-axis, long-axis and short-axis slices", fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(DOCS / "comparison.png", dpi=80)
    plt.close(fig)


def cetus():
    points_file = CETUS / "Patient7_points.json"
    if not points_file.is_file():
        print("CETUS data not available")
        return
    points = json.loads(points_file.read_text())
    spacing = points["assumed_spacing_mm"]
    fig, axes = plt.subplots(2, 3, figsize=(13, 9.5))
    for row, phase in enumerate(("ED", "ES")):
        vol = Volume(np.load(CETUS / points[phase]["file"]), spacing=(spacing,) * 3, no_data_value=0)
        apex = np.array(points[phase]["apex_index"][::-1], float) * spacing
        base = np.array(points[phase]["base_index"][::-1], float) * spacing
        r = segment(vol, apex, base)
        mask = r.mask(vol)
        for ax, view in zip(axes[row], _views(vol, (apex + base) / 2)):
            ax.imshow(view(vol.array), cmap="gray", interpolation="nearest")
            ax.contour(view(mask), [0.5], colors="yellow", linewidths=1.0)
            ax.set_xticks([])
            ax.set_yticks([])
        axes[row, 0].set_ylabel(f"{phase}: {r.volume_ml:.0f} mL ({1000 * r.seconds:.0f} ms)")
    fig.suptitle("CETUS Patient 7 (CC BY-NC-SA 4.0, Bernard et al., IEEE TMI 2016), spheroseg defaults; "
                 f"volumes assume {spacing} mm voxels", fontsize=10)
    fig.tight_layout()
    fig.savefig(DOCS / "cetus_patient7.png", dpi=70)
    plt.close(fig)


if __name__ == "__main__":
    comparison()
    cetus()
    print("wrote", DOCS / "comparison.png", DOCS / "cetus_patient7.png")
