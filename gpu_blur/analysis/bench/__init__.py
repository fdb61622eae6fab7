"""Accuracy against time: what each accuracy knob of the pipeline costs, on every backend.

``gpu-blur bench`` (and ``bench/accuracy_vs_time.py``) runs one fixed input, 9 frames made
from the built-in photograph (upscaled, the camera panning :data:`PAN_PX` pixels per frame),
through :func:`gpu_blur.synthesize` for every setting of every knob in :data:`KNOBS`, on numpy
(the float64 reference) and on every OpenCL and Warp device present, and reports for each:

* **time**: milliseconds per megapixel of output, the median of at least :data:`MIN_RUNS` runs
  after one warm-up run (which builds the kernels). Frames start in host memory and the result
  ends there, so every device is synchronized before the clock stops. Each row's runs alternate
  with as many runs of its knob's accurate setting on the same backend, so both medians (and
  their ratio, ``time_vs_accurate``) see the same load on the host;
* **error of the final image without noise** (``noise.model = "none"`` with the RAW round trip
  kept, ``isp.round_trip = "always"``): max abs error and PSNR against the numpy float64 run of
  the knob's accurate setting (its ``reference``), float output (``output.bits = 0``) so that
  errors below one 8-bit code show;
* **noise**: the KL divergence between the residuals (final image with noise minus the same
  run without noise, same seed and sample index) of the reference and of this run, RSBlur's
  measure of noise realism (supplementary Sec. 13; :func:`gpu_blur.analysis.metrics.histogram_kl`,
  one bin per 8-bit code).

A knob whose scene key or value is not offered (the scene refuses it) is reported as not
available, as is a run that fails on one backend (with its error). Side by side, from the
same run: our demosaicing against OpenCV's and colour-demosaicing's, our kernel blur against
``cv2.filter2D``, and every backend's whole pipeline against the numpy reference.

``--quick`` runs two settings per knob at :data:`QUICK_SIZE`. A progress bar shows the steps
done, the time taken and the time left; the JSON file is rewritten as each row finishes
(``"complete": false`` until the end), and the same command run again finishes it, refusing
one whose options differ.

Outputs: ``accuracy_vs_time_<tag>.json`` (every number and the devices),
``accuracy_vs_time_<tag>.md`` (the tables) and ``accuracy_vs_time_<tag>.png`` (error against
time, one series per backend and device, the Pareto front marked).
"""

from gpu_blur.analysis.bench.host import device_tag, source_digest
from gpu_blur.analysis.bench.plot import pareto_front, write_plot
from gpu_blur.analysis.bench.run import main, run_benchmark
from gpu_blur.analysis.bench.workload import (
    KNOBS,
    MIN_RUNS,
    QUICK_SIZE,
    Setting,
    quick_knobs,
    select_knobs,
)

__all__ = ["KNOBS", "MIN_RUNS", "QUICK_SIZE", "Setting", "device_tag", "main", "pareto_front",
           "quick_knobs", "run_benchmark", "select_knobs", "source_digest", "write_plot"]
