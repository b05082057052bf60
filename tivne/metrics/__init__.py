"""Pure evaluation metrics: trajectory (ATE, RPE), surface (accuracy, completion, ghosts), image (PSNR, SSIM, LPIPS)."""
