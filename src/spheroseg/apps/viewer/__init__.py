"""``spheroseg view``: a local web page to place apex, base and landmarks on a
study and watch the surface evolve (:mod:`.session` the study's state,
:mod:`.server` the HTTP side, ``static/`` the page with NiiVue vendored).

>>> from spheroseg.viewer import open_viewer                # doctest: +SKIP
>>> server = open_viewer("Patient1_frame01.mhd", port=0)    # doctest: +SKIP
>>> server.serve_in_thread(); print(server.url)             # doctest: +SKIP
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .server import ViewerServer
from .session import Points, Session

__all__ = ["open_viewer", "ViewerServer", "Session", "Points"]


def open_viewer(path, *, port: int = 0, points=None, save_root=None, spacing=None, no_data_value="auto",
                token: str | None = None, **options) -> ViewerServer:
    """Load a study and make its viewer's server (not yet serving).

    Parameters
    ----------
    path : str or Path
        A 3D image or a 3D+t sequence (anything :func:`spheroseg.io.load_frames` reads).
    port : int
        Port on 127.0.0.1 (0: a free one).
    points : str or Path, optional
        A 3D Slicer markups file (apex, base, annulus, landmarks): the first
        frame is segmented from them at once.
    save_root : str or Path, optional
        The folder under which the page may save (default: the current one).
    spacing, no_data_value
        As :func:`spheroseg.load`.
    token : str, optional
        The secret the page must carry (default: a new random one).
    **options
        :class:`spheroseg.SegmentOptions`.
    """
    from ...io import load_frames, read_markups

    frames = load_frames(path, spacing=spacing, no_data_value=no_data_value)
    start = None
    if points is not None:
        marks = read_markups(points)
        start = Points(apex=marks["apex"], base=marks["base"], landmarks=np.reshape(marks["landmarks"], (-1, 3)),
                       annulus=np.reshape(marks["annulus"], (-1, 3)))
    session = Session(frames, source=path, save_root=Path.cwd() if save_root is None else save_root, points=start,
                      spacing_assumed=spacing is not None, **options)
    try:
        return ViewerServer(session, port=port, token=token)
    except BaseException:  # the port taken, say: the session's worker stops first
        session.close()
        raise
