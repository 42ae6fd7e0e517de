"""The training-free single-view path: template retrieval, verification by rendering, contour alignment, depth ICP and its near-symmetry hypotheses."""
