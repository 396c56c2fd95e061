"""sl4slam: dense SLAM from an uncalibrated monocular camera on the SL(4) manifold (VGGT-SLAM)."""

__version__ = "0.1.0"
