"""Image and geometry metrics: PSNR, SSIM, LPIPS, depth / normal error, surface F1."""
