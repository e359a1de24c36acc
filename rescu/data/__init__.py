"""Datasets: the synthetic benchmark (``synth``, with its pinhole ``camera`` and instance
``textures``), the package photos (``photos``) and the image table of a run
(``datasets``). Per-image results and files are read and written by :mod:`rescu.io`.
Nothing is imported here.
"""
