#!/usr/bin/env bash
# Nsight Compute profiles of the render core (march, cell bounds and grid kernels), written to
# the folder given (default benchmarks/results). Needs a CUDA device and `ncu` on the PATH.
#
#   bash benchmarks/ncu_profiles.sh [outdir]
#
# Full-section reports (speed of light, occupancy, launch, warp states, memory) of one launch of
# each kernel named below, from the third frame on (the first frames compile and warm up), and
# the per-kernel times of whole frames (no cache flush, no clock lock: as the frames run).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
out=${1:-$here/results}
mkdir -p "$out"
prof="python3 $here/profile_march.py"
sections=(--section SpeedOfLight --section Occupancy --section LaunchStats
          --section WarpStateStats --section MemoryWorkloadAnalysis --section ComputeWorkloadAnalysis)
times=(--cache-control none --clock-control none --metrics gpu__time_duration.sum --csv)

# the iso march at 1M atoms, 1920x1080: classical and warped density
ncu --kernel-name regex:iso_march --launch-skip 2 --launch-count 1 "${sections[@]}" \
    $prof --atoms 1000000 --frames 4 > "$out/ncu_round3_iso_march_1m_1080p.txt"
ncu --kernel-name regex:iso_march --launch-skip 2 --launch-count 1 "${sections[@]}" \
    $prof --atoms 1000000 --frames 4 --scale-space warped > "$out/ncu_round3_iso_march_warped_1m_1080p.txt"
# the cell bounds at 1M atoms (the walk over the cells the coarse bound left open, with the
# bounds of their parts below PART_ATOMS)
ncu --kernel-name regex:"bound_kernel|bound_settle" --launch-skip 4 --launch-count 2 "${sections[@]}" \
    $prof --atoms 1000000 --frames 4 > "$out/ncu_round3_bounds_1m_1080p.txt"
# the grid build at 10M atoms: keys and ranks, the counting sort, cell weights, spread (nine
# launches a frame: setup, keys, place, order_cells, cell_weight, three spreads, total)
ncu --kernel-name regex:"keys_kernel|place_kernel|order_cells|cell_weight|spread_kernel|radix|setup_kernel|total_kernel" \
    --launch-skip 18 --launch-count 9 "${sections[@]}" \
    $prof --atoms 10000000 --frames 4 > "$out/ncu_round3_grid_10m.txt"
# per-kernel times of whole frames
ncu "${times[@]}" $prof --atoms 1000000 --frames 3 > "$out/ncu_round3_frame_1m_1080p.csv"
ncu "${times[@]}" $prof --atoms 10000000 --frames 3 > "$out/ncu_round3_frame_10m_1080p.csv"
