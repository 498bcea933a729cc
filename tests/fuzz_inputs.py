"""Seeded fuzzing of every input reader: real and generated files, mutated as files get broken
in the field (truncated, bytes flipped or inserted, numbers replaced by nan, inf, huge or
negative values, lines dropped, duplicated or swapped, a byte-order mark, CRLF), each read by
its reader. A reader may refuse a file only with the project's own errors (PancamGraphError);
anything else escaping is a finding. `tests/formats/test_fuzz_readers.py` runs a few hundred; run
`python tests/fuzz_inputs.py N` for more (the issue-15 figure: 20,000; issue 57's: 40,000).
Besides the byte-level mutations, a TOML key's value is replaced by one of another type (a list or
table where a scalar is expected)."""

from __future__ import annotations

import random
import re
import shutil
import sys
import tempfile
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pancam_graph.errors import PancamGraphError

HERE = Path(__file__).parent
REAL = HERE / "data" / "real"
SHARED_REAL = HERE.resolve().parent.parent / "shared" / "data" / "real"  # ../shared beside the checkout
NUMBER = re.compile(rb"-?\d+(\.\d+)?(e[-+]?\d+)?")
TRANSFORMS = (b"start_world_T_body = [", b"body_T_left = [")  # 4x4s in a manifest, as tomli_w writes them
REPLACEMENTS = [b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"-1", b"0", b"", b"abc", b"9223372036854775808",
                b"1" * 400, b"1e-320", b"\xff\xfe", b"\x00", b'"', b"[", b"=", b","]


MUTATIONS = ("truncate", "flip", "insert", "number", "number", "number", "drop_line", "dup_line", "swap_lines", "bom",
             "crlf", "huge_field", "transform", "transform", "type", "type")
ASSIGNMENT = re.compile(rb"^([ \t]*[A-Za-z_][\w.]*[ \t]*=[ \t]*)(.+)$", re.M)
# a TOML value of the wrong type: a list or a table where a scalar is expected, and the reverse
WRONG_TYPES = [b"[1.0]", b"[]", b"{a = 1}", b'"x"', b"true", b"[[1, 2], [3]]", b"1.5", b'["a", 2]']


def mutate(data: bytes, rng: random.Random, kinds: tuple[str, ...] = MUTATIONS) -> tuple[bytes, str]:
    """One or two mutations of a file's bytes, and their names."""
    names = []
    for _ in range(rng.choice((1, 1, 2))):
        kind = rng.choice(kinds)
        names.append(kind)
        if kind == "truncate" and data:
            data = data[:rng.randrange(len(data))]
        elif kind == "flip" and data:
            b = bytearray(data)
            for _ in range(rng.randint(1, 5)):
                b[rng.randrange(len(b))] = rng.randrange(256)
            data = bytes(b)
        elif kind == "insert":
            i = rng.randrange(len(data) + 1)
            data = data[:i] + bytes(rng.randrange(256) for _ in range(rng.randint(1, 8))) + data[i:]
        elif kind == "number":
            matches = list(NUMBER.finditer(data))
            if matches:
                m = rng.choice(matches)
                data = data[:m.start()] + rng.choice(REPLACEMENTS) + data[m.end():]
        elif kind == "type":  # a TOML key's value replaced by one of another type
            matches = list(ASSIGNMENT.finditer(data))
            if matches:
                m = rng.choice(matches)
                data = data[:m.start(2)] + rng.choice(WRONG_TYPES) + data[m.end(2):]
        elif kind == "transform":  # one entry of a rigid transform scaled, negated, zeroed or replaced
            starts = [data.find(key) + len(key) for key in TRANSFORMS if key in data]
            spans = [(a, data.find(b"\n]", a) % (len(data) + 1)) for a in starts]  # to its end, or the file's
            numbers = [m for a, b in spans for m in NUMBER.finditer(data, a, b)]
            if numbers:
                m = rng.choice(numbers)
                value = float(m.group()) * rng.choice((0.0, -1.0, 2.0, 1.001, 1.0000001)) + rng.choice((0.0, 0.5))
                text = rng.choice((repr(value).encode(), rng.choice(REPLACEMENTS)))
                data = data[:m.start()] + text + data[m.end():]
        elif kind in ("drop_line", "dup_line", "swap_lines"):
            lines = data.split(b"\n")
            if len(lines) > 1:
                i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
                if kind == "drop_line":
                    del lines[i]
                elif kind == "dup_line":
                    lines.insert(j, lines[i])
                else:
                    lines[i], lines[j] = lines[j], lines[i]
            data = b"\n".join(lines)
        elif kind == "bom":
            data = b"\xef\xbb\xbf" + data
        elif kind == "crlf":
            data = data.replace(b"\n", b"\r\n")
        elif kind == "huge_field":
            i = rng.randrange(len(data) + 1)
            data = data[:i] + b"9" * 200_000 + data[i:]
    return data, "+".join(names)


NAMED_REFUSALS = {"duplicate track": ("a second time",),
                  "non-rigid transform": ("not a rotation", "expected [0, 0, 0, 1]")}


@dataclass
class Target:
    """A reader and the files it reads: `read(folder)` reads `files` (names in a folder made from
    `seed_folder`, one of which is mutated per trial)."""

    name: str
    seed_folder: Path
    files: list[str]
    read: Callable[[Path], object]
    mutations: tuple[str, ...] = MUTATIONS


@dataclass
class Findings:
    trials: Counter = field(default_factory=Counter)
    refused: Counter = field(default_factory=Counter)  # the project's own errors
    # refusals by what they name: a track twice at a stop or in a frame, a transform not rigid
    named: Counter = field(default_factory=Counter)
    escaped: list[str] = field(default_factory=list)  # anything else: bugs


def targets(work: Path) -> list[Target]:
    """Seed files for every reader, written into `work`."""
    import dataclasses
    import datetime as dt

    import gpxpy.gpx
    import numpy as np
    from scipy.spatial.transform import Rotation

    from pancam_graph.config import RenderConfig, bundled_scenarios, load_scenario
    from pancam_graph.formats.calibration import read_stereo_calibration, write_opencv_yaml
    from pancam_graph.formats.gps_logs import read_gps_file, read_gpx, read_kfgins
    from pancam_graph.formats.trajectories import read_trajectory
    from pancam_graph.render.scenario_images import raw_stereo_pair
    from pancam_graph.sim import simulate
    from pancam_graph.store.observation_folder import read_observations
    from pancam_graph.store.observation_manifest import PanoramaImage
    from pancam_graph.store.observation_writer import write_observations

    scenario_dir = work / "scenario"
    scenario_dir.mkdir()
    shutil.copy(bundled_scenarios()["short_trail"], scenario_dir / "s.toml")

    scenario = load_scenario(bundled_scenarios()["short_trail"])
    scenario = scenario.model_copy(update={"path": scenario.path.model_copy(
        update={"waypoints": scenario.path.waypoints[:2]})})
    traverse, truth = simulate(scenario, 1)
    obs = work / "observations"
    write_observations(obs, traverse, scenario.estimator, 1, truth, scenario.rig)

    images = work / "images"  # an image folder with a body-fixed pair: frames.csv, panorama_frames.csv
    pan = [PanoramaImage(s.index, s.site_id, camera, f.pan_rad, f.tilt_rad, f"p/{s.index}_{i}_l.png",
                         f"p/{s.index}_{i}_r.png" if camera == "wac" else None)
           for s in traverse.stops if s.site_id is not None for i, f in enumerate(s.panorama)
           for camera in ("wac", "hrc")]
    mounted = traverse.rig.body_T_left(0.0, traverse.traverse_tilt_rad).matrix()
    write_observations(images, dataclasses.replace(traverse, body_T_nav_left=mounted), scenario.estimator, 1,
                       frames=[(f"l/{k:04d}.png", f"r/{k:04d}.png") for k in range(len(traverse.stops))],
                       panorama_frames=pan)

    gps = work / "gps"
    gps.mkdir()
    kfgins_lines = (REAL / "kfgins" / "GNSS-RTK.txt").read_text().splitlines(keepends=True)[:40]
    (gps / "fixes.txt").write_text("".join(kfgins_lines))
    fixes = read_kfgins(gps / "fixes.txt")
    (gps / "fixes.csv").write_text("time_s,lat_deg,lon_deg,h_m,sigma_h_m,sigma_v_m\n" + "".join(
        f"{f.time_s},{f.lat_deg!r},{f.lon_deg!r},{f.h_m},1.0,2.0\n" for f in fixes))
    g = gpxpy.gpx.GPX()
    track = gpxpy.gpx.GPXTrack()
    segment = gpxpy.gpx.GPXTrackSegment()
    t0 = dt.datetime(2020, 1, 1, tzinfo=dt.UTC)
    segment.points = [gpxpy.gpx.GPXTrackPoint(f.lat_deg, f.lon_deg, elevation=f.h_m,
                                              time=t0 + dt.timedelta(seconds=i)) for i, f in enumerate(fixes)]
    track.segments.append(segment)
    g.tracks.append(track)
    (gps / "fixes.gpx").write_text(g.to_xml())
    (gps / "fixes.nmea").write_text(_nmea(fixes))

    calib = work / "calibration"
    calib.mkdir()
    write_opencv_yaml(calib / "stereo.yaml", raw_stereo_pair(traverse.rig.wac, traverse.rig.baseline_m,
                                                            RenderConfig()))
    shutil.copy(REAL / "katwijk_pancam_calib" / "PanCam_calibstruct.mat", calib / "pancam.mat")

    poses = work / "poses"
    poses.mkdir()
    shutil.copy(obs / "truth.kitti", poses / "truth.kitti")
    q = Rotation.from_matrix(truth.world_T_body[:, :3, :3]).as_quat()
    tum = np.column_stack([np.arange(len(q), dtype=float), truth.world_T_body[:, :3, 3], q])
    np.savetxt(poses / "truth.tum", tum, fmt="%.9f")

    shutil.copy(bundled_scenarios()["mars_excerpt"], scenario_dir / "mars.toml")
    mars = load_scenario(bundled_scenarios()["mars_excerpt"])
    mars = mars.model_copy(update={"path": mars.path.model_copy(update={"waypoints": mars.path.waypoints[:3]})})
    mars_traverse, _ = simulate(mars, 1)
    mars_obs = work / "mars_observations"  # sun_heading.csv and the orbital map's GeoTIFFs: the image
    # records and the truth left out, which the observations target reads already (and slowly)
    write_observations(mars_obs, mars_traverse.keeping(set()), mars.estimator, 1, None, mars.rig)
    maps = sorted(f"maps/{p.name}" for p in (mars_obs / "maps").iterdir())

    from pancam_graph.formats.mslice import read_mslice_locations
    from pancam_graph.formats.pds import read_rover_images, site_origins

    curiosity = SHARED_REAL / "curiosity_navcam_sol26_57"
    products = work / "pds"  # two real Curiosity products (labels and browse images) and MSLICE's file
    products.mkdir()
    if curiosity.is_dir():  # else the target is left out (../shared is not beside the checkout)
        for stem in ("NLA_399801979EDR_D0030382TRAV00006M", "NLA_399802006EDR_D0030386TRAV00006M"):
            shutil.copy(curiosity / "sol0026" / f"{stem}1.LBL", products)
            shutil.copy(curiosity / "sol0026" / f"{stem}_.jpg", products)
        locations = (curiosity / "mslice_locations_sol0_59.xml").read_text().split("</location>")
        (products / "mslice_locations.xml").write_text("</location>".join(locations[:6]) + "</location>\n</msl>\n")

    def read_products(d: Path):
        images = read_rover_images(d)
        site_origins(images)
        return images, read_mslice_locations(d / "mslice_locations.xml")

    from pancam_graph.sources import pds as pds_source

    pds4_products = work / "pds4"  # two stops' stereo pairs as PDS4 products (tests/formats/test_pds4.py's)
    pds4_products.mkdir()
    _write_pds4_products(pds4_products)

    return [
        Target("scenario", scenario_dir, ["s.toml"], lambda d: load_scenario(d / "s.toml")),
        Target("mars scenario", scenario_dir, ["mars.toml"], lambda d: load_scenario(d / "mars.toml")),
        Target("mars folder", mars_obs, [n for n in ("traverse.toml", "sun_heading.csv") if (mars_obs / n).is_file()],
               read_observations),
        Target("geotiff maps", mars_obs, maps, read_observations),
        *([Target("pds labels", products, sorted(p.name for p in products.iterdir()), read_products)]
          if curiosity.is_dir() else []),
        Target("pds4 labels", pds4_products, sorted(p.name for p in pds4_products.iterdir()), pds_source.load),
        Target("observations", obs, sorted(p.name for p in obs.iterdir()), read_observations),
        Target("image folder", images, sorted(p.name for p in images.iterdir()), read_observations),
        Target("transforms", images, ["traverse.toml"], read_observations, ("transform",)),
        Target("gps csv", gps, ["fixes.csv"], lambda d: read_gps_file(d / "fixes.csv", 1.0, 1.0)),
        Target("kf-gins", gps, ["fixes.txt"], lambda d: read_gps_file(d / "fixes.txt")),
        Target("gpx", gps, ["fixes.gpx"], lambda d: read_gpx(d / "fixes.gpx", 1.0, 1.0)),
        Target("nmea", gps, ["fixes.nmea"], lambda d: read_gps_file(d / "fixes.nmea", 1.0, 1.0)),
        Target("opencv yaml", calib, ["stereo.yaml"], lambda d: read_stereo_calibration(d / "stereo.yaml")),
        Target("matlab", calib, ["pancam.mat"], lambda d: read_stereo_calibration(d / "pancam.mat",
                                                                                   image_size=(1280, 960))),
        Target("kitti poses", poses, ["truth.kitti"], lambda d: read_trajectory(d / "truth.kitti")),
        Target("tum", poses, ["truth.tum"], lambda d: read_trajectory(d / "truth.tum")),
    ]


def _nmea(fixes) -> str:
    import pynmea2
    lines = []
    for i, f in enumerate(fixes):
        t = f"{12 + i // 3600:02d}{(i // 60) % 60:02d}{i % 60:02d}.00"
        lat = f"{int(f.lat_deg):02d}{(f.lat_deg % 1) * 60:010.7f}"
        lon = f"{int(f.lon_deg):03d}{(f.lon_deg % 1) * 60:010.7f}"
        lines.append(str(pynmea2.RMC("GP", "RMC", (t, "A", lat, "N", lon, "E", "0.0", "0.0", "010120", "", ""))))
        lines.append(str(pynmea2.GGA("GP", "GGA", (t, lat, "N", lon, "E", "4", "12", "0.8", f"{f.h_m:.4f}", "M",
                                                    "0.0", "M", "", ""))))
    return "\n".join(lines) + "\n"


def fuzz(trials: int, seed: int = 0, keep: Path | None = None) -> Findings:
    rng = random.Random(seed)
    findings = Findings()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        all_targets = targets(work)
        for target in all_targets:  # the unmutated files read
            target.read(target.seed_folder)
        for trial in range(trials):
            target = all_targets[trial % len(all_targets)]
            name = rng.choice(target.files)
            folder = work / "trial"
            if folder.exists():
                shutil.rmtree(folder)
            shutil.copytree(target.seed_folder, folder)
            data, how = mutate((target.seed_folder / name).read_bytes(), rng, target.mutations)
            (folder / name).write_bytes(data)
            if keep is not None:  # a native crash kills the process: the last file tells which
                shutil.copy(folder / name, keep / f"last_{target.name}_{name}".replace(" ", "_").replace("/", "_"))
                (keep / "last.txt").write_text(f"{trial} {target.name} {name} {how}\n")
            findings.trials[target.name] += 1
            try:
                target.read(folder)
            except PancamGraphError as exc:
                findings.refused[target.name] += 1
                for what, words in NAMED_REFUSALS.items():
                    if any(w in str(exc) for w in words):
                        findings.named[what] += 1
            except Exception as exc:  # the finding: anything else escaping a reader
                frames = traceback.extract_tb(exc.__traceback__)
                ours = [f for f in frames if "pancam_graph" in f.filename] or frames
                where = " < ".join(f"{Path(f.filename).name}:{f.lineno}" for f in (frames[-1], ours[-1]))
                findings.escaped.append(f"{target.name} {name} ({how}): {type(exc).__name__}: {str(exc)[:160]} "
                                        f"[{where}]")
    return findings


def _write_pds4_products(folder: Path) -> None:
    """Two stops' stereo pairs of small textured images, as PDS4 products."""
    from pancam_graph.formats.pds4 import ProductDescription, write_product
    from pancam_graph.geometry.cahvor import from_photogrammetric
    from pancam_graph.geometry.rig import Camera

    camera = Camera(60.0, 60.0, 31.5, 23.5, 64, 48, k1=-0.2, k2=0.1)
    rover_R_camera = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    rng = np.random.default_rng(0)
    for k in range(2):
        site_T_rover = np.eye(4)
        site_T_rover[0, 3] = 1.5 * k
        for eye, y in (("LEFT", -0.2), ("RIGHT", 0.2)):
            model = from_photogrammetric(camera, rover_R_camera, np.array([0.1, y, -1.5]), eye)
            product = ProductDescription(f"NAV_{eye}_{k:04d}", 1.7e9 + 60.0 * k, "TEST ROVER", f"NAV_{eye}", 1, k,
                                         0, site_T_rover, None, model)
            write_product(folder, product, rng.integers(0, 255, (48, 64), dtype=np.uint8))


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 2000
    keep = Path(sys.argv[3]) if len(sys.argv) > 3 else None
    result = fuzz(n, seed=int(sys.argv[2]) if len(sys.argv) > 2 else 0, keep=keep)
    for name in sorted(result.trials):
        print(f"{name:14s} {result.trials[name]:6d} files, {result.refused[name]:6d} refused with a message")
    for what in NAMED_REFUSALS:
        print(f"refused naming a {what}: {result.named[what]}")
    print(f"{len(result.escaped)} escaped")
    for line in Counter(e.split(": ", 1)[1] for e in result.escaped).most_common(40):
        print(" ", line)

