#!/usr/bin/env bash
# GPU check: every study's tiny config, one training epoch and the filter, point-mass and
# navigator benchmarks at a small size, on CUDA and on the CPU, in one run, with the ratio of
# their wall times. Run from the repository root on a CUDA machine:
#
#   bash benchmarks/gpu_check.sh            # needs CUDA; refuses cleanly without it
#   bash benchmarks/gpu_check.sh --dry-run  # CPU for both legs: checks the script itself
#
# Nothing is claimed for CUDA until this has been run on one. The benchmarks run with
# --device (their NumPy / FilterPy / scipy references stay on the CPU, so a benchmark's wall
# ratio understates its torch rows: the GPU leg's own table, printed after the summary, has
# the per-row rates; bench_navigator's one-vehicle latencies are launch-bound on a GPU, its
# batched row is the one to read). Every command is bounded (PER_RUN_S, default 120 s) so
# the whole check stays under 10 minutes. Outputs go to a temporary folder; exit 0 when
# every leg ran.
set -u
cd "$(dirname "$0")/.." || exit 2
PER_RUN_S="${PER_RUN_S:-120}"
GPU=cuda
if [ "${1:-}" = "--dry-run" ]; then
  GPU=cpu
elif ! python -c 'import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)'; then
  echo "error: no CUDA device here (torch.cuda.is_available() is False); run this on a GPU" \
       "machine, or pass --dry-run to check the script on the CPU." >&2
  exit 2
fi
OUT="$(mktemp -d)"
trap 'rm -rf "$OUT"' EXIT
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
failed=0

# Wall seconds of one command (empty when it failed), its output in $OUT/<tag>.log.
timed() {
  local tag="$1"; shift
  local t0 t1
  t0=$(date +%s.%N)
  if timeout "$PER_RUN_S" "$@" >"$OUT/$tag.log" 2>&1; then
    t1=$(date +%s.%N)
    python -c "print(f'{$t1 - $t0:.2f}')"
  else
    echo ""
  fi
}

row() {  # name, cpu seconds, gpu seconds
  local ratio="n/a"
  if [ -n "$2" ] && [ -n "$3" ]; then
    ratio=$(python -c "print(f'{$2 / $3:.2f}x')")
  fi
  printf '| %-28s | %8s | %8s | %8s |\n' "$1" "${2:-failed}" "${3:-failed}" "$ratio"
  if [ -z "$2" ] || [ -z "$3" ]; then failed=1; fi
}

echo "device for the GPU leg: $GPU"
python -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda,
  torch.cuda.get_device_name(0) if torch.cuda.is_available() else "(no CUDA device)")'
echo
echo "| run                          |  CPU [s] |  GPU [s] | CPU/GPU  |"
echo "|------------------------------|---------:|---------:|---------:|"
accel=gpu; [ "$GPU" = cpu ] && accel=cpu
train=(python train.py --data.path synthetic:64 --trainer.max_epochs 1 --runs_dir "$OUT/train")
cpu=$(timed train-cpu "${train[@]}" --trainer.accelerator cpu)
gpu=$(timed train-gpu "${train[@]}" --trainer.accelerator "$accel")
row "train.py, one epoch" "$cpu" "$gpu"
# The tan studies fly the tiny scenario's tile: an untrained map of it (the plumbing only).
MAP="$OUT/tiny_map.pt"
python - "$MAP" <<'PY'
import sys, torch
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.export import save_map
torch.manual_seed(0)
tile = scenario_tile(load_scenario("tiny"))
save_map(BlockwiseTerrainNet.from_tile(tile, hidden=8, n_frequencies=4), sys.argv[1])
PY
# A short straight flight over synthetic:64 for the flight study (INS 25 m off, radar with
# 3 m noise, the truth as reference), as its end-to-end test writes one.
python - "$OUT/log.csv" <<'PY'
import csv, sys
import numpy as np, torch
from neuralmap.dem.load import load_tile
from neuralmap.terrain.grid import GridTerrain
tile = load_tile("synthetic:64")
xmin, xmax, ymin, ymax = tile.extent
s = np.linspace(0.25, 0.75, 60)
truth = np.stack([xmin + s * (xmax - xmin), ymin + s * (ymax - ymin)], -1)
with torch.no_grad():
    ground = GridTerrain(tile, method="bicubic")(torch.as_tensor(truth)).numpy()
h = ground.max() + 250.0
radar = h - ground + np.random.default_rng(4).normal(0.0, 3.0, len(s))
with open(sys.argv[1], "w", newline="") as handle:
    w = csv.writer(handle)
    w.writerow(["time", "ins_x", "ins_y", "ins_h", "radar", "ref_x", "ref_y", "ref_h"])
    for k in range(len(s)):
        w.writerow([float(k), *(truth[k] + [25.0, -15.0]), h, radar[k], *truth[k], h])
PY
for config in configs/*_tiny.yaml; do
  name=$(basename "$config" .yaml)
  study=$(python -c "import sys, yaml; print((yaml.safe_load(open(sys.argv[1])) or {}).get('study', ''))" "$config")
  extra=()
  case "$study" in
    "") continue ;;  # a training config (latent_map_tiny, learn_noise_tiny)
    tan|tan_outliers) extra=(--map "$MAP") ;;
    flight) extra=(--log "$OUT/log.csv") ;;
  esac
  cpu=$(timed "$name-cpu" python evaluate.py --config "$config" --device cpu --runs_dir "$OUT/runs" --progress false "${extra[@]}")
  if [ "$study" = gnss_ins ]; then  # its simulation stays on the CPU; the study refuses --device cuda
    printf '| %-28s | %8s | %8s | %8s |\n' "$name" "${cpu:-failed}" "cpu only" "n/a"
    [ -z "$cpu" ] && failed=1
    continue
  fi
  gpu=$(timed "$name-gpu" python evaluate.py --config "$config" --device "$GPU" --runs_dir "$OUT/runs" --progress false "${extra[@]}")
  row "$name" "$cpu" "$gpu"
done
# The benchmarks at a small size (each leg well under PER_RUN_S on 2 CPU cores).
bench_sizes() {
  case "$1" in
    bench_filter) echo "--n 20000 --n_neural 5000 --n_filterpy 10 --n_queries 100000 --n_scipy 2000 --steps 5 --repeats 2 --skip_policies" ;;
    bench_point_mass) echo "--runs 1000 --steps 5 --ref_runs 1 --repeats 1 --sweep 32" ;;
    bench_navigator) echo "--quick" ;;
  esac
}
for bench in bench_filter bench_point_mass bench_navigator; do
  read -r -a size <<<"$(bench_sizes "$bench")"
  cpu=$(timed "$bench-cpu" python "benchmarks/$bench.py" "${size[@]}" --device cpu)
  gpu=$(timed "$bench-gpu" python "benchmarks/$bench.py" "${size[@]}" --device "$GPU")
  row "$bench" "$cpu" "$gpu"
done
for bench in bench_filter bench_point_mass bench_navigator; do
  if [ -s "$OUT/$bench-gpu.log" ]; then
    echo
    echo "== benchmarks/$bench.py on $GPU (small size; its table):"
    grep -E '^\||cell-upd/s|^batched|^point-mass|^NumPy|^memory|memory bandwidth|^neuralmap Navigator|^map  |^grid \(|^latent map  |^latent map baked|vehicles batched|^targets met' \
      "$OUT/$bench-gpu.log" | head -n 40
  fi
done
if [ "$failed" -ne 0 ]; then
  echo
  echo "some runs failed; their logs:"
  for log in "$OUT"/*.log; do echo "== $log"; tail -n 5 "$log"; done
  trap - EXIT
  echo "(logs kept in $OUT)"
  exit 1
fi
