"""``python -m gpu_blur.cli``: the ``gpu-blur`` command."""

import sys

from gpu_blur.cli import main

sys.exit(main())
