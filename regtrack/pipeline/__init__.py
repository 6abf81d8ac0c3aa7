"""End-to-end pipeline: stage orchestration and the content-addressed stage cache."""
