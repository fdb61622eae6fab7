"""``python -m gpu_blur.analysis.bench``: the same as ``gpu-blur bench``."""

import sys

from gpu_blur.analysis.bench.run import main

sys.exit(main())
