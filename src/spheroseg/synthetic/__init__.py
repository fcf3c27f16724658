"""Synthetic echocardiography with its truth: the ground the method is
measured on, apart from the method itself (nothing in the core imports it).

- :mod:`spheroseg.synthetic.echo`: image formation (point-spread function,
  speckle, log compression, a scanner's post-processing) of a scene.
- :mod:`spheroseg.synthetic.phantom`: scenes of a left ventricle (tilt,
  phase, papillary muscles, trabeculae, epicardium, a late region) and
  sequences over a cycle, with their true masks and volumes.
"""
