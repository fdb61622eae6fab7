"""Analysis tools: they measure cameras, images and the synthesis itself; none of them synthesizes.

* :mod:`gpu_blur.analysis.calibrate`: a camera file from a colour chart (white balance, colour
  correction, photometric alignment, camera response);
* :mod:`gpu_blur.analysis.align`: geometric alignment of a real blurred image and its frames;
* :mod:`gpu_blur.analysis.metrics`: PSNR, SSIM, residual KL divergence, noise level;
* :mod:`gpu_blur.analysis.bench`: accuracy against speed of every backend (``gpu-blur bench``).
"""

__all__: list[str] = []
