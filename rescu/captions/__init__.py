"""Captions (paper section 6): a base caption enhanced with the counts and the scene.

``caption`` holds the captioners and :func:`~rescu.captions.caption.caption_result`.
Nothing is imported here.
"""
