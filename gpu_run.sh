#!/usr/bin/env bash
# one GPU session: tests, golden, benches (untracked scratch; deleted before stopping)
export PYTHONPATH=$PWD:/tmp/site OCL_ICD_VENDORS=/tmp/vendors
mkdir -p /tmp/vendors; echo /usr/lib/libnvidia-opencl.so.1 > /tmp/vendors/nvidia.icd
git log --oneline -1 > $OUT/commit.txt 2>/dev/null || echo "no git" > $OUT/commit.txt
nvidia-smi --query-gpu=name,driver_version --format=csv > $OUT/gpu.txt
T0=$(date +%s)
GPU_BLUR_BACKENDS=numpy,opencl:0:0,warp:cuda:0 timeout 150 python3 -m pytest -q -p no:cacheprovider -x \
  tests/test_warp_backend.py tests/test_synthesizer.py tests/test_outputs.py > $OUT/tests.txt 2>&1
echo "tests rc=$? $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
GPU_BLUR_BACKENDS=opencl:0:0,warp:cuda:0 timeout 100 python3 tests/golden.py --check tests/data/golden_outputs.json > $OUT/golden.txt 2>&1
echo "golden rc=$? $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
timeout 80 python3 bench/batch_vs_synthesize.py --backend warp:cuda:0 --batch 16 --runs 5 --json $OUT/bvs_warp.json > $OUT/bvs.txt 2>&1
echo "bvs rc=$? $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
timeout 40 python3 -c "
import cProfile, pstats, torch, numpy as np, gpu_blur
synth = gpu_blur.Synthesizer('realblur_j', backend='warp:cuda:0')
rng = np.random.default_rng(0); x = torch.from_numpy(rng.random((16, 1200, 1920, 3), dtype=np.float32)).cuda(); m = (x > 0.95).float()
synth(x, mask=m); torch.cuda.synchronize()
pr = cProfile.Profile(); pr.enable()
for i in range(3): synth(x, mask=m, first_index=16 * (i + 1))
torch.cuda.synchronize(); pr.disable()
pstats.Stats(pr).sort_stats('tottime').print_stats(30)
" > $OUT/profile_torch.txt 2>&1
echo "profile rc=$? $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
timeout 200 python3 bench/generate_gpu.py --backend warp:cuda:0 --samples 24 --workers 1,2,4 --json $OUT/generate_gpu.json > $OUT/generate.txt 2>&1
echo "generate rc=$? $(( $(date +%s) - T0 )) s" >> $OUT/times.txt
