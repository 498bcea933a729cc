"""Write KITTI sequence 00's real stereo tracks and GPS, as GTSAM's wheel ships them, as an
observation folder (docs/frontend.md, "Leave one out"):

    python scripts/kitti00_observation_folder.py OUT
    pancam-graph run OUT --configs vo

The manifest selects the real-image VO error model; the fixes are the reference (vs_gps in
metrics.json) and feed the configurations with gps."""

from __future__ import annotations

import sys
from pathlib import Path

from pancam_graph.config import EstimatorConfig
from pancam_graph.formats.gtsam_kitti import fit_start, kitti00_traverse, read_kitti00_example
from pancam_graph.store.observation_folder import write_observations


def main(out: Path) -> None:
    example = read_kitti00_example()
    start = fit_start(example)
    traverse = kitti00_traverse(example, start)
    write_observations(out, traverse, EstimatorConfig(vo_error_model="real_images"), seed=0)
    print(f"{out}: {len(traverse.stops)} stops, {len(traverse.gps_fixes)} GPS fixes; start fitted on the "
          f"example's VO: clock offset {start.clock_offset_s:.3f} s, its scale {start.scale:.4f}, "
          f"horizontal RMS {start.rms_m:.2f} m over {start.fixes} fixes")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(Path(sys.argv[1]))
