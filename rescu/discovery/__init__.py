"""Stage I (RESCU-I, paper section 3): recurring patterns from SIFT features.

The data flows ``features`` (SIFT keypoints and descriptors) -> ``urp`` (unit recurring
patterns: affinities and gates between feature pairs) -> ``search`` (the pattern search
over URPs) -> ``stage1`` (RP matrices, instances and the RESCU-I result); ``grasp`` is the
GRASP baseline on the same features. Nothing is imported here: importing a subpackage
stays as cheap as importing the module a job needs.
"""
