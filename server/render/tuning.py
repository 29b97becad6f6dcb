"""How the renderer trades its own work: every switch and threshold that changes how long a frame
takes but not what it shows (the tests hold each one's image to the default's, or within the
accuracy its docstring names), in one place.

`Tuning` is what a caller may set (benchmarks and tests do; the server keeps the defaults); the
module constants below are the rules the defaults follow, each with the reason it holds and the
results file it was measured in (`benchmarks/results/`; the rounds' history is in
`benchmarks/HISTORY.md`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from server.render.errors import RenderError
from server.render.grid import GRID_SORTS

PartMode = Literal["all", "visible", "none"]
PART_MODES: tuple[PartMode, ...] = ("all", "visible", "none")
"""`part_bounds`: every open cell walked for its part bounds, only those the view reaches (the
others walk whole), or whole cells only."""

# ----------------------------------------------------------------- rules of the defaults

MARCH_REGISTERS = {"gaussian": 64, "carved": 64, "geodesic": 64}
"""Register cap of each density's iso kernels (0: the compiler's): 64 keeps more warps in flight
than 80 for the classical and carved densities (render_h200_round4_regs_sizes.json), and for
the geodesic one, whose march took 254 registers uncapped (one block of 8 warps per
multiprocessor): 0.41-0.85x the frame time, but 1.03x at 5,684 atoms
(render_h200_geodesic_registers.json)."""
VOLUME_REGISTERS = 64
"""Register cap of the volume kernel: fewer registers, more warps
(render_h200_round4_regs_volume.json); measured again with segments (render_h200_volume_regs.json,
render_h200_volume_regs_10k.json): 64 stays the fastest at 1M atoms (12.6 ms; 96: 14.9, 128:
15.6, none: 24.4) and at villin; 96-128 would save 7 % at 10,000 atoms."""
VOLUME_STEPS = 2
"""Volume mode marches twice the iso lattice's step, its segments integrating the density's ramp
between samples: 1.3-1.6x faster than the sample sum at one step (render_h200_volume_segments.json).
Against the converged image (volume_accuracy.json, 8-bit levels) a sharp transfer function
errs less than the sum did at one step (shells: mean 0.49 against 0.65, largest 16 against 22);
the default cloud errs a little more (mean 0.51 against 0.22, largest 9 against 3)."""
CELLS_PER_CUTOFF = {"gaussian": 2.0, "carved": 1.0, "geodesic": 2.0}
"""Grid cells per cutoff of each density: the carved density's Gaussians reach 0.6 sigma k and
its walks want larger cells (render_h100_variants_warped*.json)."""
BOUND_KEEP_FROM = {"gaussian": 8.0, "carved": math.inf, "geodesic": 8.0}
"""Per density, the multiple of the level from which an empty cell keeps its coarse bound
unwalked: few such walks end below the level for the classical bound, while the carved density's
coarse bound ignores its factor (render_h200_round3_parts_keep.json)."""
VISIBLE_ATOMS = 500_000
"""From this many atoms only the cells the view reaches walk for part bounds (walking every
cell costs with the atoms, the samples it saves with the surface in view;
render_h200_round5_visible*.json)."""
VIEW_ATOMS = 700_000
"""Atoms per view of one set of positions from which walking every open cell pays
(render_h200_round6_views*.json)."""
STILL_VIEWS = 8
"""Views of still positions after which the grid walks every open cell (a turning camera over a
paused system; render_h200_round6_views*.json)."""
LARGE_ATOMS = 30_000_000
"""From this many atoms the grid has one cell per cutoff and volume frames walk whole cells: the
bounds of 1.4 cells per atom cost more than finer skipping saves (render_h100_scale.json)."""
TRIAL_ATOMS = 100_000
"""Below this many atoms a CUDA renderer times its part-bound choice against whole cells
(`parttrial.py`): whole cells won by 6-16 % at 2,500-10,000 atoms and lost by 20-37 % from
30,000 atoms in every run (render_h200_part_trial*.json, render_h200_parts_iso.json). From
here a trial could only lose: a live 1M-atom server once kept whole cells after its turns were
timed amid the stream's other device work (a cast of 7.3 ms against 5.5)."""
PIPELINE_ATOMS = 1_000_000
"""From this many atoms a CUDA renderer keeps two positions buffers (an upload overlaps the
render before it); below, an upload takes under 0.1 ms and one buffer keeps one graph per
frame set-up."""
MARCH_BLOCK = 256
"""Threads per block of the marching kernels (render_h100_split.json, "blocks")."""
MARCH_BUDGET = 6
"""Density passes an iso ray takes in the first marching kernel when rays are split; rays that
need more are queued for the second (render_h100_split.json, "budgets")."""
SPLIT_LANES = 8
SPLIT_RAYS = 16384
"""The second marching kernel gives each queued ray SPLIT_LANES threads that march consecutive
stretches of it, SPLIT_LANES * SPLIT_RAYS threads striding over the queue."""
SPLIT_PIXELS_PER_SM = 8 * 1024
SPLIT_MIN_ATOMS = 4096
"""Rays are split automatically on CUDA for images of at most SPLIT_PIXELS_PER_SM pixels per
multiprocessor (too few rays to fill the GPU) of molecules of at least SPLIT_MIN_ATOMS atoms
(rays long enough to be worth it; the budget sweep of render_h100_split.json)."""
GRAPH_CACHE = 8
"""CUDA graphs kept per renderer, least recently used dropped: one per distinct frame set-up
(one per viewer camera when viewers hold their own)."""
VIEWS_KEPT = 64
"""Views a grid remembers having walked the cells of (forgetting one only repeats a walk)."""


@dataclass(frozen=True)
class Tuning:
    """The renderer's switches; None picks the rule above. None of them changes an image except
    `taper` (off: each Gaussian cut at the cutoff, a baseline for the taper's cost),
    `fixed_cutoff` and `geodesic_volume` (the surface moves within the accuracy bound),
    `refine_passes` (an iso hit moves within its bracket), `volume_steps` and `volume_ramps`
    (a volume image moves within the accuracy `volume_accuracy.py` measures);
    `empty_space_skipping` off marches every lattice sample, the same image slower."""

    cells_per_cutoff: float | None = None
    """Grid cell = cutoff / this (>= 1; the cell grows where memory caps the count)."""
    empty_space_skipping: bool = True
    fast_math: bool = True
    """CUDA's approximate transcendentals."""
    max_registers: int | None = None
    """Register cap of the iso kernels on CUDA (0: the compiler's)."""
    volume_max_registers: int = VOLUME_REGISTERS
    graphs: bool | None = None
    """Replay repeated frame set-ups as captured graphs (None: on CUDA only)."""
    march_budget: int | None = None
    """Passes an iso ray takes before it is queued for `split_lanes` threads (0: never split)."""
    split_lanes: int = SPLIT_LANES
    double_buffer: bool | None = None
    """Two positions buffers, so an upload overlaps the render before it."""
    bound_keep_from: float | None = None
    """Multiple of the level from which an empty cell keeps its coarse bound (inf: walk all)."""
    grid_sort: str = "counting"
    part_bounds: PartMode | None = None
    part_trial: bool | None = None
    """Time the rule of sizes' part bounds against whole cells on the renderer's own frames
    and keep the faster (`parttrial.py`; None: on CUDA, where a frame's device time is
    measured; off when `part_bounds` is set)."""
    count_passes: bool = False
    """Rays count their density passes (`Renderer.read_pass_counts`; kernels of their own)."""
    taper: bool = True
    fixed_cutoff: bool = False
    """Reach cutoff_sigmas exactly, not the least the surface's accuracy needs (reach.py): the
    baseline of the accuracy reach's gain."""
    mean_lanes: int | None = None
    """Threads per sampled atom of the mean density (None: density.LANES_PER_SAMPLE on CUDA,
    geodesic_field.MEAN_LANES_PER_SAMPLE for the geodesic density's, 1 on the CPU; 1 is the
    baseline)."""
    decided_sides: bool | None = None
    """The marching kernels ask a density only for each sample's side of the level where it
    can tell it sooner than the value (`DensityModel.side4`: the geodesic density); off,
    every sample that may reach the level is evaluated whole. None: on for the CPU device,
    off on CUDA, where a warp still waits for its slowest ray. Geodesic frames with it against
    without: 0.67-0.71x the time on two CPU cores (render_cpu_2core_geodesic_sides.json),
    0.98-1.44x on one NVIDIA H200 (render_h200_geodesic_sides.json)."""
    refine_passes: int | None = None
    """Passes that cut an iso crossing's interval into fifths before its secant step (None:
    raycast.REFINE_PASSES); each pass is one `value4` per pixel."""
    volume_steps: int = VOLUME_STEPS
    """Volume mode's step in steps of the iso lattice (`step_sigmas`); it changes the image
    within the accuracy `volume_accuracy.py` measures."""
    volume_ramps: bool = True
    """Volume segments integrate the density's ramp between their samples (segments.py); off:
    each sample's density is held over its segment (the sum before, the baseline)."""
    geodesic_volume: bool | None = None
    """The geodesic density's rays read it from a grid evaluated once a frame
    (`geodesic_volume`; the surface moves within max(0.05 A, 1 % sigma)): None when the grid
    has at most `geodesic_volume.points_per_pixel` points a pixel (160 on CUDA, 6 on the CPU),
    True whenever it fits, False never (the routes walked per sample, the baseline)."""
    geodesic_bricks: bool | None = None
    """The geodesic grid's fill walks, for each point of a brick of 32 (one warp), the atoms
    within reach of the whole brick, so its threads read the same routes together; off, each
    point walks the atoms within reach of itself (the same values bit for bit, the baseline).
    None: on CUDA only."""
    geodesic_fill_lanes: int | None = None
    """Groups of 32 threads that take one brick of the geodesic grid's fill together, each a
    share of every row's atoms (None: `GeodesicVolume.lanes_for` the grid's size; 1 on the
    CPU)."""
    cpu_threads: int | None = None
    """Host threads the CPU device's heaviest launches are split across: the march, the
    shading and the volume cast as runs of the image's tiles, the geodesic grid's fill as runs
    of its listed bricks (None: `device.host_threads`, the cores this process may use; 1: the
    renderer's own thread alone, the baseline). CUDA devices take none."""
    geodesic_fill_registers: int | None = None
    """Register cap of the geodesic grid's fill kernel on CUDA (None:
    `geodesic_volume.FILL_REGISTERS`; 0: the compiler's). Its transcendentals follow
    `fast_math`."""
    bound_lanes: int | None = None
    """Threads that walk one listed cell's part bounds together on CUDA, each a share of every
    row's atoms (None: `renderer.BOUND_LANES` for a grid that lists its cells in a buffer of
    its own, a small molecule's few hundred to few thousand cells, 1 for larger grids, whose
    lists fill the device; 1 is the baseline). Always 1 on the CPU, whose tiles are one
    thread wide."""
    cell_list: bool = True
    """A grid with more cells than twice its atoms lists the cells its bound walks in a buffer
    of its own (off: in the atoms' spare buffer, the baseline: the cells it leaves out are
    walked one thread each)."""

    def __post_init__(self) -> None:
        if self.march_budget is not None and self.march_budget < 0:
            raise RenderError(f"march_budget must be >= 0, got {self.march_budget}")
        if self.split_lanes < 1:
            raise RenderError(f"split_lanes must be >= 1, got {self.split_lanes}")
        if self.grid_sort not in GRID_SORTS:
            raise RenderError(
                f"grid_sort must be one of {', '.join(GRID_SORTS)}, got {self.grid_sort!r}"
            )
        if self.bound_keep_from is not None and not self.bound_keep_from >= 1.0:
            raise RenderError(f"bound_keep_from must be >= 1, got {self.bound_keep_from}")
        if self.part_bounds is not None and self.part_bounds not in PART_MODES:
            raise RenderError(
                f"part_bounds must be one of {', '.join(PART_MODES)}, got {self.part_bounds!r}"
            )
        if self.geodesic_fill_lanes is not None and self.geodesic_fill_lanes < 1:
            raise RenderError(f"geodesic_fill_lanes must be >= 1, got {self.geodesic_fill_lanes}")
        if self.cpu_threads is not None and self.cpu_threads < 1:
            raise RenderError(f"cpu_threads must be >= 1, got {self.cpu_threads}")
        regs = self.geodesic_fill_registers
        if regs is not None and (isinstance(regs, bool) or not 0 <= regs <= 255):
            raise RenderError(f"geodesic_fill_registers must be 0-255, got {regs!r}")
        if self.mean_lanes is not None and self.mean_lanes < 1:
            raise RenderError(f"mean_lanes must be >= 1, got {self.mean_lanes}")
        if self.bound_lanes is not None and not 1 <= self.bound_lanes <= 1024:
            raise RenderError(f"bound_lanes must be in [1, 1024], got {self.bound_lanes}")
        if self.refine_passes is not None and self.refine_passes < 0:
            raise RenderError(f"refine_passes must be >= 0, got {self.refine_passes}")
        if self.volume_steps < 1:
            raise RenderError(f"volume_steps must be >= 1, got {self.volume_steps}")
        if self.cells_per_cutoff is not None and not self.cells_per_cutoff >= 1.0:
            raise RenderError(f"cells_per_cutoff must be >= 1, got {self.cells_per_cutoff}")

    @classmethod
    def of(cls, options: dict[str, object]) -> Tuning:
        """A tuning from a mapping of its fields (benchmarks' JSON options); an unknown name is
        refused with the names there are."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(options) - known)
        if unknown:
            raise RenderError(
                f"unknown tuning {', '.join(unknown)} (known: {', '.join(sorted(known))})"
            )
        return cls(**options)  # type: ignore[arg-type]
