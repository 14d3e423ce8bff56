"""The paper's baselines: ``covariance`` (3D covariance features and a random forest) and
what they share (``common``: prediction runs written as submissions).

Nothing is imported here: ``import semantic3d.baselines.covariance`` loads scikit-learn only
when a name that needs it is used.
"""
