"""Scene analysis from recurring patterns (paper section 5).

``vp`` (vanishing points from RPs and the LSD line baseline), ``symmetry`` (3D
translation symmetry by cross ratios), ``completion`` (missing instances of rows and
grids), ``counting`` (dominant pattern and counts) and ``analyse`` (the scene step that
calls them in turn on one image result). The row geometry all of them share lives in
:mod:`rescu.layout`. Nothing is imported here.
"""
