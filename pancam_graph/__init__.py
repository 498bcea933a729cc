"""pancam_graph: rover localization over long traverses with a GTSAM factor graph."""

__version__ = "0.1.0"
