#!/usr/bin/env bash
# The checks only a CUDA GPU can run, in one go; CI has no GPU and skips them.
#
#   bash scripts/check_gpu.sh            # PYTHON=python3 and OUT_DIR=gpu_check by default
#
# 1. tests/test_cuda.py: Hertz impacts, a CPU run followed, checkpoints between devices, compiled
#    kernels and a small draw down, on the GPU.
# 2. scripts/bench_engine.py --device cuda: the dense box at B = 1, 16 and 64, float32 and
#    float64, eager and then compiled. No LIGGGHTS here: compare with the CPU figures in
#    docs/performance.md.
# 3. scripts/bench_drawdown.py: the default slice as one ensemble of 16 replicates on the GPU,
#    compiled (the fill is placed on the CPU).
#
# Each step's output goes to OUT_DIR, and a failed step does not stop the next. Each step has a
# time limit (seconds: TEST_S, ENGINE_S, DRAWDOWN_S). Cost measured on an H100 (torch 2.11): a
# slice member steps in 2.1 ms compiled, and 16 eager members in 8-9 ms (docs/performance.md,
# "On a GPU").
set -u
python=${PYTHON:-python3}
out=${OUT_DIR:-gpu_check}
mkdir -p "$out"
run() {  # name, seconds, command...
    local name=$1 seconds=$2 started=$SECONDS
    shift 2
    timeout "$seconds" "$@" > "$out/$name.out" 2> "$out/$name.log"
    echo "$name: exit $? after $((SECONDS - started)) s (output in $out/$name.out, log in $out/$name.log)"
}
$python -c "import torch; assert torch.cuda.is_available(), 'no CUDA device'; print(torch.__version__, torch.cuda.get_device_name())" || exit 1
run test_cuda "${TEST_S:-300}" env TORCHDEM_NO_EXTENSION=1 $python -m pytest -q -p no:cacheprovider tests/test_cuda.py -rA
tail -n 12 "$out/test_cuda.out"
engine=(scripts/bench_engine.py --device cuda --no-liggghts --batches 1,16,64 --dtypes float32,float64
        --headline-dtype float32 --json)
run bench_engine_eager "${ENGINE_S:-600}" $python "${engine[@]}"
run bench_engine_compiled "${ENGINE_S:-600}" $python "${engine[@]}" --compile
for f in bench_engine_eager bench_engine_compiled; do
    $python - "$out/$f.out" <<'EOF'
import json, sys
try:
    d = json.load(open(sys.argv[1]))
except (OSError, ValueError) as err:
    sys.exit(f"{sys.argv[1]}: no figures ({err})")
keys = sorted(k for k in d if k.startswith("particle_steps_per_s_b") and k.count("_") == 5)
print(sys.argv[1], d["device_name"], "compile" if d["compile"] else "eager",
      ", ".join(f"{k[21:]} {d[k]:.3g}" for k in keys), "particle-steps/s")
EOF
done
run bench_drawdown "${DRAWDOWN_S:-900}" $python scripts/bench_drawdown.py --json --skip-single --batch 16 \
    sim.device=cuda sim.compile=true
grep -v Warning "$out/bench_drawdown.log" | tail -n 3
