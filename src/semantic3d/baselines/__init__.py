"""The paper's three baselines: ``covariance`` (3D covariance features and a random forest),
``cnn`` (the 3D CNN) and ``image`` (2D segmentation of cube maps), and what they share
(``common``: prediction runs written as submissions). Each one's docs page lists where it
differs from the paper.

Nothing is imported here: ``import semantic3d.baselines.covariance`` loads scikit-learn only
when a name that needs it is used.
"""
