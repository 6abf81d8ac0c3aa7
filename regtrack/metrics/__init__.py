"""Registration metrics of Lapuebla-Ferri et al. plus distance statistics and Dice."""

from regtrack.metrics.metrics import (
    DistanceStats,
    Metrics,
    compression_degree,
    compute_metrics,
    dice,
    distance_stats,
    similarity_percent,
)

__all__ = ["DistanceStats", "Metrics", "compression_degree", "compute_metrics", "dice",
           "distance_stats", "similarity_percent"]
