"""Synthesis: realistic blurred samples from sharp input, as a scene describes, in batches.

The public names are :func:`synthesize`, :class:`Synthesizer`, :class:`Synthesis` and
:class:`Batch` (also :mod:`gpu_blur`'s). The modules, one job each:

    synthesizer.py  the public API: synthesize() (a batch of one) and Synthesizer, which holds
                    the pieces below and picks the path its samples run on
    results.py      what comes back: Synthesis (one sample), Batch, the outputs' crop
    inputs.py       input checks: synthesize()'s inputs read and laid out, values, sizes,
                    frame counts, sample indices, codes=
    batches.py      batch input and output: array types and layouts, out= arrays, codes made
                    on the host, the JPEG stage
    draws.py        each sample's plan (made once per clip test and size) and drawn values
    resident.py     the device-resident path of kernel backends (ResidentPath): inputs put
                    once, checks by device counts, every pass once per plan for the batch
    host.py         the host path (HostPath): tiles, memory budgets, spot checks through
                    gpu_blur.scheduler; render_sharp, the sharp reference on the host
"""

from gpu_blur.synthesis.results import Batch, Synthesis
from gpu_blur.synthesis.synthesizer import Synthesizer, synthesize

__all__ = ["Batch", "Synthesis", "Synthesizer", "synthesize"]
