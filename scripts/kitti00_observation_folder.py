"""Write KITTI sequence 00's real stereo tracks and GPS, as GTSAM's wheel ships them, as an
observation folder (docs/frontend.md, "Leave one out"):

    python scripts/kitti00_observation_folder.py OUT [TRUTH]
    pancam-graph run OUT --configs vo

TRUTH is a folder with KITTI's ground truth of the sequence, poses.txt(.gz) and times.txt
(default: tests/data/real/kitti00_ground_truth). With it the frames get their real times, the
start and the clock offset are fitted on the truth against every fix of the drive, and the
folder carries the frames' true poses (truth.kitti): a run is judged against the truth and the
fixes. It starts at frame 16, where the truth becomes trustworthy
(gtsam_kitti.TRUTH_FIRST_FRAME). Without it (TRUTH = none) the start and clock come from the
example's own VO poses and the fixes are the only reference. The manifest selects the
real-image VO error model."""

from __future__ import annotations

import sys
from pathlib import Path

from pancam_graph.config import EstimatorConfig
from pancam_graph.errors import PancamGraphError
from pancam_graph.formats.gtsam_kitti import (
    fit_start,
    kitti00_on_truth,
    kitti00_traverse,
    read_kitti00_example,
    read_kitti00_truth,
)
from pancam_graph.store.observation_writer import write_observations

DEFAULT_TRUTH = Path(__file__).resolve().parents[1] / "tests" / "data" / "real" / "kitti00_ground_truth"


def main(out: Path, truth_folder: Path | None) -> None:
    example = read_kitti00_example()
    if truth_folder is None:
        start, truth = fit_start(example), None
        traverse = kitti00_traverse(example, start)
        how = f"start fitted on the example's VO (its scale {start.scale:.4f})"
    else:
        traverse, truth, start = kitti00_on_truth(example, read_kitti00_truth(truth_folder))
        how = "start and frame times from KITTI's ground truth, fitted on every fix of the drive"
    write_observations(out, traverse, EstimatorConfig(vo_error_model="real_images"), seed=0, truth=truth)
    print(f"{out}: {len(traverse.stops)} stops, {len(traverse.gps_fixes)} GPS fixes; {how}: clock offset "
          f"{start.clock_offset_s:.3f} s, horizontal RMS {start.rms_m:.2f} m over {start.fixes} fixes")


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        sys.exit(__doc__)
    given = sys.argv[2] if len(sys.argv) == 3 else str(DEFAULT_TRUTH)
    try:
        main(Path(sys.argv[1]), None if given == "none" else Path(given))
    except PancamGraphError as exc:
        sys.exit(f"error: {exc}")
