"""Record what the descent computes, to pin it through a restructuring.

Run from the repository root on the commit whose results are the reference:

    python tests/data/make_descent_reference.py
    python tests/data/make_descent_reference.py --track-only   # the sequence only

It writes ``tests/data/descent_reference.npz``: for each phantom family x
data term, the iteration count and the final Hermite coefficients; and a
short tracked sequence with a user landmark.  ``tests/test_tracker.py``
requires today's code to reproduce them to 1e-10.  The reference in the
repository was made on commit 92d46fa (round 1's last), before the descent
was split into a tracker, data terms and backends; its tracked sequence
was made again (``--track-only``) when frames that moved further than the
finest level follows came to be segmented again from the coarse data term,
and when the initial shape's candidate among them came to be smoothed
towards that shape fitted to its coarse levels' volume.
"""

from pathlib import Path

import numpy as np

from spheroseg.synthetic.phantom import FAMILIES, make_phantom, make_sequence
from spheroseg.tracking.segment import segment, track

MODES = ("local", "chan-vese", "fast")
SPACING = 1.5
# every option the reference depends on, spelled out: later defaults may change
OPTIONS = dict(system="prolate", patches=(8, 8), step=1.0, max_iterations=60, tol=0.05, coarse_to_fine=True,
               band=8.0, band_out=15.0, nu=0.0, smoothness=1.0, landmark_weight=1.0, apex_weight=1.0, order=8,
               radius_ratio=0.3)


def cases():
    """(name, volume, apex, base, extra keywords) of every recorded segmentation."""
    for k, (family, kwargs) in enumerate(FAMILIES.items()):
        ph = make_phantom(seed=200 + k, spacing=SPACING, **kwargs)
        for mode in MODES:
            yield f"{family}/{mode}", ph.volume, ph.apex, ph.base, dict(mode=mode)


def sequence():
    return make_sequence(seed=7, n_frames=4, spacing=2.0)


#: the options of the tracked sequence since frames that moved too far are
#: segmented again (tests/test_tracker.py tracks with them)
TRACK_OPTIONS = dict(adaptive_step=False, coarse_tol=0.05, mode="local", follow_base=False)


def main(track_only: bool = False) -> None:
    out = Path(__file__).with_name("descent_reference.npz")
    if track_only:  # the segmentations as recorded on 92d46fa, the sequence again
        record = {k: v for k, v in np.load(out).items() if not k.startswith("track/")}
    else:
        record = {}
        for name, volume, apex, base, extra in cases():
            res = segment(volume, apex, base, **OPTIONS, **extra)
            record[f"{name}/iterations"] = res.iterations
            record[f"{name}/coefficients"] = res.surface.coefficients
    seq = sequence()
    first = seq.frames[0]
    landmark = first.base + 0.6 * (first.apex - first.base) + np.array([0.0, 14.0, 0.0])
    tr = track(seq.volumes, first.apex, first.base, landmarks=[landmark], iterations_per_frame=5, **OPTIONS,
               **(TRACK_OPTIONS if track_only else {}))
    record["track/iterations"] = np.array([f.iterations for f in tr.frames])
    record["track/coefficients"] = np.stack([f.surface.coefficients for f in tr.frames])
    np.savez_compressed(out, **record)
    print(f"wrote {out} ({out.stat().st_size} bytes)")


if __name__ == "__main__":
    import sys

    main(track_only="--track-only" in sys.argv[1:])
