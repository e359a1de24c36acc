"""Datasets: the synthetic benchmark (``synth``, with its pinhole ``camera`` and instance
``textures``), the package photos (``photos``), the image table of a run
(``datasets``) and one tiny photo for examples (``example``). Per-image results and files are read and written by :mod:`rescu.io`.
Nothing is imported here.
"""
