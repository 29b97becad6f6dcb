#!/usr/bin/env bash
# Nsight Compute profiles of the render core (march, shading, cell bounds, the marks of the
# view and grid kernels), written to the folder given (default benchmarks/results) with the
# round's name in front (default round6). Needs a CUDA device and `ncu` on the PATH.
#
#   bash benchmarks/ncu_profiles.sh [outdir] [round]
#
# Full-section reports (speed of light, occupancy, launch, warp states, memory) of one launch of
# each kernel named below, from the third frame on (the first frames compile and warm up), and
# the per-kernel times of whole frames (no cache flush, no clock lock: as the frames run).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
out=${1:-$here/results}
round=${2:-round6}
mkdir -p "$out"
prof="python3 $here/profile_march.py"
sections=(--section SpeedOfLight --section Occupancy --section LaunchStats
          --section WarpStateStats --section MemoryWorkloadAnalysis --section ComputeWorkloadAnalysis)
times=(--cache-control none --clock-control none --metrics gpu__time_duration.sum --csv)

# the iso march at 1M atoms, 1920x1080: classical and warped density
ncu --kernel-name regex:iso_march --launch-skip 2 --launch-count 1 "${sections[@]}" \
    $prof --atoms 1000000 --frames 4 > "$out/ncu_${round}_iso_march_1m_1080p.txt"
ncu --kernel-name regex:iso_march --launch-skip 2 --launch-count 1 "${sections[@]}" \
    $prof --atoms 1000000 --frames 4 --scale-space warped > "$out/ncu_${round}_iso_march_warped_1m_1080p.txt"
# the iso shading at 1M atoms
ncu --kernel-name regex:iso_shade --launch-skip 2 --launch-count 1 "${sections[@]}" \
    $prof --atoms 1000000 --frames 4 > "$out/ncu_${round}_iso_shade_1m_1080p.txt"
# the cell bounds at 1M atoms, four launches a frame: the settle and walk of whole cells, the
# marks of the cells the view reaches, and the walk of their parts
ncu --kernel-name regex:"bound_kernel|bound_settle|mark_kernel" --launch-skip 8 --launch-count 4 \
    "${sections[@]}" $prof --atoms 1000000 --frames 4 > "$out/ncu_${round}_bounds_1m_1080p.txt"
# the grid build at 10M atoms: keys and ranks, the counting sort, gather, cell weights, spread
# (ten launches a frame: setup, ranked keys, place, order_cells, total, gather, cell_weight,
# three spreads)
ncu --kernel-name regex:"keys_kernel|place_kernel|order_cells|gather_atoms|cell_weight|spread_kernel|setup_kernel|total_kernel" \
    --launch-skip 20 --launch-count 10 "${sections[@]}" \
    $prof --atoms 10000000 --frames 4 > "$out/ncu_${round}_grid_10m.txt"
# per-kernel times of whole frames
ncu "${times[@]}" $prof --atoms 1000000 --frames 3 > "$out/ncu_${round}_frame_1m_1080p.csv"
ncu "${times[@]}" $prof --atoms 10000000 --frames 3 > "$out/ncu_${round}_frame_10m_1080p.csv"
