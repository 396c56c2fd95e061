"""Neural models used by the pipeline (VGGT, DINOv2, SALAD), implemented in plain PyTorch."""
