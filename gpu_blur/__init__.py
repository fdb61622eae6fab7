"""gpu_blur: realistic motion-blur synthesis (RSBlur, Rim et al. ECCV 2022) on CPUs and GPUs."""
