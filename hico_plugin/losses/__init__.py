"""Losses: photometric (L1 + D-SSIM) and depth-normal geometric consistency (DNGC)."""
