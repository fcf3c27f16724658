"""Live tracking over OpenIGTLink: ``spheroseg live`` and ``spheroseg replay``.

This subpackage owns the network path from a scanner's stream to 3D
Slicer: :mod:`~spheroseg.apps.live.messages` (the OpenIGTLink v2 messages: the
stream split and checked, IMAGE decoded, POLYDATA, IMAGE, TRANSFORM and
STRING encoded), :mod:`~spheroseg.apps.live.fanout` (a server sending the newest
messages to every client), :mod:`~spheroseg.apps.live.replay` (a PLUS-like
sender of a 3D+t sequence), :mod:`~spheroseg.apps.live.session` (frames tracked
one by one as :func:`spheroseg.track` tracks them, the cardiac cycle found
on the fly), :mod:`~spheroseg.apps.live.server` (the live tracker between a
source and its clients), :mod:`~spheroseg.apps.live.client` (a results client)
and :mod:`~spheroseg.apps.live.commands` (the two subcommands).  It needs
nothing beyond spheroseg's own dependencies (pyigtl, the ``live`` extra, is
the tests' reference for the messages); nothing here is imported by
``import spheroseg``.
"""
