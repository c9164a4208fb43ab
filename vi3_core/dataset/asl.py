"""EuRoC ASL folders (``mav0/``): reading and writing, byte-compatible with the layout EuRoC ships.

Layout: ``cam0/data/<ns>.png`` (mono8) + ``cam0/data.csv`` + ``cam0/sensor.yaml``, ``imu0/data.csv`` +
``imu0/sensor.yaml``, ``state_groundtruth_estimate0/data.csv`` (p, q as w x y z, v, gyro bias, accel bias, all
in EuRoC's column order) + ``sensor.yaml``, ``body.yaml``.

Extra folder, ``depth0/``: ground-truth z-depth of cam0 frames (metres along the optical axis, per pixel). Read in
any of these forms (``read_depth_source``):

- what ``vi3 make-bag`` writes: one 16-bit PNG per cam0 frame, ``data/<ns>.png`` listed in ``depth0/data.csv``,
  value = depth in metres x ``DEPTH_SCALE`` (0.25 mm steps, up to 16.38 m), 0 = no depth, on the *undistorted*
  cam0 grid (pinhole intrinsics ``calib.undistorter().K``); ``depth0/sensor.yaml`` states ``depth_scale`` and
  ``undistorted_K``;
- float depth: ``data/<ns>.npy`` (2-D float array, metres; 0, negative or non-finite = no depth);
- 16-bit PNG in millimetres (TUM/ETH3D-style datasets): ``data/<ns>.png`` without a ``sensor.yaml``, or with a
  ``sensor.yaml`` whose ``depth_scale`` (units per metre, e.g. 5000 for TUM RGB-D) says otherwise.

Files are listed in ``depth0/data.csv`` or, without it, found by name (``<ns>`` = the cam0 frame's stamp). Depth is
on the raw (distorted) cam0 grid unless ``sensor.yaml`` gives ``undistorted_K``; raw-grid depth is carried onto the
undistorted grid by ``Sequence.gt_depth`` (nearest neighbour through the undistortion map). A ``depth0/`` that cannot
be used leaves the sequence without depth and says why in ``Sequence.depth_gt`` ("unreadable: ...").
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import yaml

from vi3_core import so3
from vi3_core.dataset.calib import CameraCalib, load_calib, write_euroc_sensor_yaml
from vi3_core.dataset.sequence import GroundTruthTrack, Sequence
from vi3_core.errors import DataError, yaml_problem
from vi3_core.paths import missing_reason
from vi3_core.sim.imu import ImuNoise
from vi3_core.types import ImuSamples

DEPTH_SCALE = 4000.0  # units per metre of the depth PNGs this project writes
PNG_MM_SCALE = 1000.0  # units per metre of 16-bit depth PNGs without a depth0/sensor.yaml (millimetres)
DEPTH_SUFFIXES = (".npy", ".png")

CAM_HEADER = "#timestamp [ns],filename"
IMU_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
GT_HEADER = ("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
             "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
             "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
             "b_a_RS_S_z [m s^-2]")
_IDENTITY_T_BS = {"cols": 4, "rows": 4, "data": [float(x) for x in np.eye(4).reshape(-1)]}


# ----------------------------------------------------------------------------------------------- reading
def find_mav0(path) -> Path:
    """The ``mav0`` folder at ``path`` or inside it."""
    path = Path(path)
    for cand in (path, path / "mav0"):
        if (cand / "cam0").is_dir():
            return cand
    raise DataError(f"{path}: not an EuRoC ASL folder (no cam0/ in it or in {path / 'mav0'})")


def iter_csv(path: Path, *, columns: int, first: str = "#timestamp") -> Iterator[tuple[int, int, list[str]]]:
    """An EuRoC csv row by row (nothing else held in memory): (row number counted from 1 after the header, stamp
    int64 ns, the other ``columns - 1`` cells stripped); blank lines are skipped. DataError naming the file (and the
    row) when it is missing, its header does not name ``columns`` columns starting with ``first``, a row has another
    number of columns or a stamp is not integer nanoseconds."""
    if not path.is_file():
        raise DataError(f"{path}: {missing_reason(path)}")
    with path.open(newline="") as f:
        header = f.readline().strip()
        names = [h.strip() for h in header.split(",")]
        if len(names) != columns or not names[0].startswith(first):
            raise DataError(f"{path}: header {header!r} is not EuRoC's: expected {columns} comma-separated columns "
                            f"starting with {first!r}")
        for row_no, row in enumerate((r for r in csv.reader(f) if r), start=1):
            if len(row) != columns:
                raise DataError(f"{path}: the number of columns changed from {columns} to {len(row)} at row "
                                f"{row_no} (rows counted after the header; the header has {columns} columns)")
            try:
                ns = int(row[0].strip())
            except ValueError:
                raise DataError(f"{path}: row {row_no}: timestamp {row[0]!r} is not integer nanoseconds") from None
            yield row_no, ns, [c.strip() for c in row[1:]]


def read_csv(path: Path, *, columns: int, first: str = "#timestamp") -> tuple[np.ndarray, list[list[str]]]:
    """A whole EuRoC csv (``iter_csv``): ([R] int64 ns, R lists of the other cells)."""
    rows = [(ns, cells) for _, ns, cells in iter_csv(path, columns=columns, first=first)]
    return np.array([ns for ns, _ in rows], dtype=np.int64), [cells for _, cells in rows]


def iter_samples(path: Path, *, columns: int, finite: int = 0) -> Iterator[tuple[int, np.ndarray]]:
    """The rows of a numeric EuRoC csv (IMU, ground truth) as (stamp ns, [columns-1] float64 values), checked as they
    come: DataError naming the file and row when it has no row at all, a value is not a number (or, among the first
    ``finite`` values, not a finite number) or a stamp is not after the previous one (a file must be sorted by
    time)."""
    last = None
    for row_no, ns, cells in iter_csv(path, columns=columns):
        try:
            values = np.array([float(c) for c in cells])
        except ValueError as err:
            raise DataError(f"{path}: row {row_no}: non-numeric value ({err})") from None
        if finite and not np.all(np.isfinite(values[:finite])):
            col = int(np.argmin(np.isfinite(values[:finite])))
            raise DataError(f"{path}: row {row_no}: {cells[col]!r} in column {col + 2} is not a finite number")
        if last is not None and ns <= last:
            raise DataError(f"{path}: its stamps are not increasing (unsorted, or a row repeated): row {row_no} "
                            f"at {ns} ns follows {last} ns; sort the file by timestamp")
        last = ns
        yield ns, values
    if last is None:
        raise DataError(f"{path}: no samples (a header and no rows)")


def _read_samples(path: Path, columns: int, *, finite: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A whole numeric EuRoC csv (``iter_samples``): ([R] int64 ns, [R, columns-1] float64), filled into arrays that
    double when full (at most twice the result's memory)."""
    ns, values, n = np.empty(1024, np.int64), np.empty((1024, columns - 1)), 0
    for t, v in iter_samples(path, columns=columns, finite=finite):
        if n == len(ns):
            ns, values = np.resize(ns, 2 * n), np.resize(values, (2 * n, columns - 1))
        ns[n], values[n] = t, v
        n += 1
    return ns[:n].copy(), values[:n].copy()


def _read_png(path: Path, flags: int) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise DataError(f"{path}: missing or not a readable PNG")
    return img


def read_depth_file(path: Path, scale: float = PNG_MM_SCALE) -> np.ndarray:
    """One depth map -> [H,W] float32 metres, NaN where there is no depth: ``.npy`` (2-D float array, metres) or
    16-bit ``.png`` (``scale`` units per metre; 0 = no depth)."""
    if path.suffix == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as err:
            raise DataError(f"{path}: not a readable .npy array ({err})") from None
        if raw.ndim == 3 and raw.shape[2] == 1:
            raw = raw[..., 0]
        if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.floating):
            raise DataError(f"{path}: depth must be a 2-D float array in metres, got {raw.dtype} {raw.shape}")
        depth = raw.astype(np.float32)
    elif path.suffix == ".png":
        raw = _read_png(path, cv2.IMREAD_UNCHANGED)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise DataError(f"{path}: depth PNGs must be single-channel 16-bit, got {raw.dtype} {raw.shape}")
        depth = raw.astype(np.float32) / np.float32(scale)
    else:
        raise DataError(f"{path}: unsupported depth file type {path.suffix!r} (use {' or '.join(DEPTH_SUFFIXES)})")
    with np.errstate(invalid="ignore"):
        depth[~(np.isfinite(depth) & (depth > 0))] = np.nan
    return depth


def _depth_meta(path: Path, K_undistorted: np.ndarray) -> tuple[float, bool]:
    """(PNG units per metre, whether the depth is on the raw grid) from ``depth0/sensor.yaml`` (absent: millimetres
    on the raw grid)."""
    if not path.is_file():
        return PNG_MM_SCALE, True
    try:
        doc = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise DataError(f"{path}: not valid YAML: {yaml_problem(err)}") from None
    if not isinstance(doc, dict):
        raise DataError(f"{path}: expected a YAML mapping, got {type(doc).__name__}")
    try:
        scale = float(doc.get("depth_scale", PNG_MM_SCALE))
    except (TypeError, ValueError):
        scale = float("nan")
    if not (np.isfinite(scale) and scale > 0):
        raise DataError(f"{path}: depth_scale must be a positive number of units per metre, got "
                        f"{doc.get('depth_scale')!r}")
    if "undistorted_K" not in doc:
        return scale, True
    K = np.asarray(doc["undistorted_K"], dtype=np.float64).reshape(-1)
    if K.size != 9 or not np.allclose(K.reshape(3, 3), K_undistorted, rtol=1e-6, atol=1e-6):
        raise DataError(f"{path}: undistorted_K {K.tolist()} is not cam0's undistorted intrinsics "
                        f"{np.asarray(K_undistorted).reshape(-1).tolist()}")
    return scale, False


def read_depth_source(depth_dir: Path, ns: np.ndarray, calib: CameraCalib) -> tuple[list[Path | None], float, bool,
                                                                                     str]:
    """The depth folder of cam0 frames ``ns`` [N] int64: (file per frame or None, PNG units per metre, whether on
    the raw grid, a description). Reads the first file to check it. Raises DataError naming why the folder cannot
    be used."""
    scale, raw_grid = _depth_meta(depth_dir / "sensor.yaml", calib.undistorter().K)
    data = depth_dir / "data"
    if (depth_dir / "data.csv").is_file():
        d_ns, cells = read_csv(depth_dir / "data.csv", columns=2)
        by_ns = {int(k): data / name for k, (name,) in zip(d_ns, cells)}
    elif data.is_dir():
        found = [f for f in data.iterdir() if f.suffix in DEPTH_SUFFIXES and f.stem.isdigit()]
        by_ns = {int(f.stem): f for f in found}
        if len(by_ns) != len(found):
            raise DataError(f"{data}: several depth files for one stamp (both .npy and .png?)")
    else:
        raise DataError(f"{depth_dir}: neither data.csv nor a data/ folder")
    files = [by_ns.get(k) for k in ns.tolist()]
    have = [f for f in files if f is not None]
    if not have:
        raise DataError(f"{depth_dir}: none of its {len(by_ns)} depth files is named after a cam0 stamp "
                        f"(expected data/<ns>{' or data/<ns>'.join(DEPTH_SUFFIXES)})")
    suffixes = {f.suffix for f in have}
    if suffixes - set(DEPTH_SUFFIXES):
        raise DataError(f"{depth_dir}: unsupported depth file types {sorted(suffixes - set(DEPTH_SUFFIXES))}")
    first = read_depth_file(have[0], scale)
    w, h = calib.size
    if first.shape != (h, w):
        raise DataError(f"{have[0]}: depth map is {first.shape[1]}x{first.shape[0]}, cam0 images are {w}x{h}")
    kinds = " and ".join(("float .npy (m)" if x == ".npy" else f"16-bit PNG ({scale:g} per m)")
                         for x in sorted(suffixes))
    grid = "raw (distorted) grid, undistorted by nearest neighbour" if raw_grid else "undistorted grid"
    return files, scale, raw_grid, f"{kinds} on the {grid}; {len(have)} of {len(ns)} frames"


def imu_csv(mav0: Path) -> Path:
    return mav0 / "imu0" / "data.csv"


def iter_imu(mav0: Path) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """imu0/data.csv row by row (``iter_samples``): (stamp ns, gyro [3] rad/s, accel [3] m/s^2)."""
    for ns, v in iter_samples(imu_csv(mav0), columns=7):
        yield ns, v[:3], v[3:]


def read_imu(mav0: Path) -> tuple[np.ndarray, ImuSamples]:
    """imu0/data.csv -> (ns [M] int64, ImuSamples); DataError when it is empty or unsorted (``iter_samples``)."""
    ns, vals = _read_samples(imu_csv(mav0), 7)
    return ns, ImuSamples(ns * 1e-9, vals[:, :3], vals[:, 3:], t_ns=ns)


def read_groundtruth(mav0: Path) -> GroundTruthTrack | None:
    """state_groundtruth_estimate0/data.csv -> track (None when the folder is absent). The pose is the truth: a
    position or rotation value that is not a finite number is a broken file (DataError naming the row). Velocities
    and biases are estimates a motion-capture file may not have (``nan``, as when a TUM trajectory is written in this
    layout): velocities with any NaN are derived from the positions (``GroundTruthTrack``), unknown biases stay NaN
    (their metrics unknown)."""
    path = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if not path.parent.is_dir():
        return None
    ns, vals = _read_samples(path, 17, finite=7)
    q_xyzw = vals[:, [4, 5, 6, 3]]
    T = so3.make_T(so3.quat_to_R(q_xyzw), vals[:, :3])
    v_WB = vals[:, 7:10] if np.isfinite(vals[:, 7:10]).all() else None
    return GroundTruthTrack(ns * 1e-9, T, v_WB=v_WB, bg=vals[:, 10:13], ba=vals[:, 13:16], t_ns=ns)


def camera_stamps_without_images(imu_ns: np.ndarray, gt: GroundTruthTrack | None, rate_hz: float) -> np.ndarray:
    """Camera stamps [N] int64 ns for a folder that has IMU and ground truth but no images: every k-th IMU stamp at
    ``rate_hz`` (as EuRoC's camera is triggered on the IMU clock), within the span both cover (a sample of margin
    each side)."""
    if gt is None or len(imu_ns) < 3:
        raise DataError("a folder without camera images needs IMU and ground truth to place camera stamps")
    t0, t1 = max(int(imu_ns[1]), int(gt.t_ns[0])), min(int(imu_ns[-2]), int(gt.t_ns[-1]))
    inside = imu_ns[(imu_ns >= t0) & (imu_ns <= t1)]
    step = max(int(round(1e9 / rate_hz / float(np.median(np.diff(imu_ns))))), 1)
    if len(inside) < 2 * step:
        raise DataError(f"IMU and ground truth overlap for {(t1 - t0) * 1e-9:.3f} s: too short for camera frames")
    return inside[::step]


def camera_frames(mav0: Path, camera: str = "cam0") -> tuple[np.ndarray, list[Path]] | None:
    """The frames ``camera``/data.csv lists, in stamp order: ([N] int64 ns, their image files); None when the
    camera has no data.csv (a folder of IMU and ground truth only). DataError when data.csv cannot be read (a broken
    symbolic link, a loop) or lists a stamp twice."""
    path = mav0 / camera / "data.csv"
    if not path.is_file():
        if path.exists() or path.is_symlink():  # a folder, a broken link, a loop: not "no images"
            raise DataError(f"{path}: {missing_reason(path)}")
        return None
    ns, cells = read_csv(path, columns=2)
    order = np.argsort(ns, kind="stable")
    ns = ns[order]
    twice = np.flatnonzero(np.diff(ns) == 0)
    if len(twice):
        raise DataError(f"{path}: stamp {ns[twice[0]]} ns is listed {int(np.sum(ns == ns[twice[0]]))} times; each "
                        "frame once")
    return ns, [mav0 / camera / "data" / cells[i][0] for i in order]


def read_frame(path: Path) -> np.ndarray:
    """One camera frame as recorded, mono8 [H,W] (a colour PNG is converted to grey); DataError when the PNG is
    missing or unreadable."""
    img = _read_png(path, cv2.IMREAD_UNCHANGED)
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def read_asl(path, *, camera: str = "cam0") -> Sequence:
    """Open an ASL folder (``mav0`` or its parent) as a Sequence; images and depth load lazily.

    A folder whose camera has a ``sensor.yaml`` but no ``data.csv`` (IMU and ground truth only, e.g. the EuRoC IMU
    test data) opens with camera stamps on the IMU clock (``camera_stamps_without_images``) and no images: it can be
    evaluated with the ground-truth pose instrument (``--backbone gt``) only."""
    mav0 = find_mav0(path)
    cam_dir = mav0 / camera
    calib = load_calib(cam_dir / "sensor.yaml")
    imu_ns, imu = read_imu(mav0)
    gt = read_groundtruth(mav0)
    frames = camera_frames(mav0, camera)
    if frames is not None:
        ns, files = frames
    else:
        ns, files = camera_stamps_without_images(imu_ns, gt, calib.rate_hz or 20.0), None
    load_depth, raw_grid, depth_gt = None, False, "none"
    if (mav0 / "depth0").is_dir():
        try:
            depth_files, scale, raw_grid, depth_gt = read_depth_source(mav0 / "depth0", ns, calib)
        except DataError as err:
            depth_gt = f"unreadable: {err}"
        else:
            def load_depth(i: int) -> np.ndarray | None:
                return None if depth_files[i] is None else read_depth_file(depth_files[i], scale)

    def load_image(i: int) -> np.ndarray:
        if files is None:
            raise DataError(f"{cam_dir}: no data.csv, so no images (an IMU and ground-truth folder: evaluate it with "
                            "--backbone gt)")
        return read_frame(files[i])

    return Sequence(name=sequence_name(mav0), stamps=ns * 1e-9, imu=imu, calib=calib, gt=gt, load_image=load_image,
                    load_depth=load_depth, stamps_ns=ns, imu_ns=imu_ns, depth_on_raw_grid=raw_grid,
                    depth_gt=depth_gt, has_images=files is not None)


def sequence_name(mav0: Path) -> str:
    """The name of the sequence in ``mav0`` (the folder holding ``cam0/``): that folder or the first one above it
    not called ``asl`` or ``mav0`` (``OUT/room/asl/mav0`` -> ``room``)."""
    mav0 = mav0.resolve()
    for folder in (mav0, *mav0.parents):
        if folder.name not in ("asl", "mav0"):
            return folder.name or "mav0"
    return "mav0"


# ----------------------------------------------------------------------------------------------- writing
def _rows(ns: np.ndarray, values: np.ndarray | None = None, names: list[str] | None = None) -> str:
    """csv rows, one per stamp: ns, then ``values`` (shortest repr, exact round trip) or ``names``."""
    cols = [np.asarray(ns, dtype=np.int64).astype(str)]
    if values is not None:
        cols += [np.array([repr(float(x)) for x in col], dtype=object) for col in np.asarray(values, np.float64).T]
    if names is not None:
        cols.append(np.asarray(names))
    return "".join(",".join(r) + "\n" for r in zip(*cols))


class AslWriter:
    """Writes the csv files of an ASL folder a block of rows at a time, in stamp order.

    Creates ``cam0/data/``, ``imu0/``, ``state_groundtruth_estimate0/`` (and ``depth0/data/`` when ``with_depth``)
    with each csv's header; ``imu``, ``groundtruth`` and ``frames`` append rows. Images go to ``image_dir`` and
    depth maps to ``depth_dir`` through ``write_image``/``write_depth``; the sensor.yaml files are written apart
    (``write_sensor_yaml`` or copies of a recording's own).
    """

    def __init__(self, mav0: Path, *, with_depth: bool) -> None:
        self.mav0 = Path(mav0)
        self.image_dir = self.mav0 / "cam0" / "data"
        self.depth_dir = self.mav0 / "depth0" / "data" if with_depth else None
        self._csv = {"cam": (self.mav0 / "cam0" / "data.csv", CAM_HEADER),
                     "imu": (self.mav0 / "imu0" / "data.csv", IMU_HEADER),
                     "gt": (self.mav0 / "state_groundtruth_estimate0" / "data.csv", GT_HEADER)}
        if self.depth_dir is not None:
            self._csv["depth"] = (self.mav0 / "depth0" / "data.csv", CAM_HEADER)
        for folder in (self.image_dir, self.depth_dir):
            if folder is not None:
                folder.mkdir(parents=True, exist_ok=True)
        for path, header in self._csv.values():
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(header + "\n")

    def _append(self, key: str, text: str) -> None:
        with self._csv[key][0].open("a") as f:
            f.write(text)

    def imu(self, ns: np.ndarray, imu: ImuSamples) -> None:
        """imu0/data.csv rows: gyro then accel."""
        self._append("imu", _rows(ns, np.concatenate([imu.gyro, imu.accel], 1)))

    def groundtruth(self, ns: np.ndarray, T_WB: np.ndarray, v_WB: np.ndarray, bg: np.ndarray,
                    ba: np.ndarray) -> None:
        """state_groundtruth_estimate0/data.csv rows: p, q (w x y z), v, gyro bias, accel bias."""
        q = so3.R_to_quat(T_WB[:, :3, :3])[:, [3, 0, 1, 2]]
        self._append("gt", _rows(ns, np.concatenate([T_WB[:, :3, 3], q, v_WB, bg, ba], 1)))

    def frames(self, ns: np.ndarray) -> None:
        """cam0/data.csv (and depth0/data.csv) rows naming ``<ns>.png``."""
        names = [f"{k}.png" for k in np.asarray(ns).tolist()]
        for key in ("cam", "depth"):
            if key in self._csv:
                self._append(key, _rows(ns, names=names))


def write_sensor_yaml(mav0: Path, calib: CameraCalib, noise: ImuNoise, *, rate_hz: float = 200.0) -> None:
    """cam0/, imu0/ (noise model) and state_groundtruth_estimate0/ sensor.yaml, and body.yaml, of a simulation."""
    write_euroc_sensor_yaml(calib, mav0 / "cam0" / "sensor.yaml", comment="VI3 rendered camera (EuRoC cam0 model)")
    doc = {"sensor_type": "imu", "comment": "VI3 simulated IMU (EuRoC ADIS16448 noise model)",
           "T_BS": _IDENTITY_T_BS, "rate_hz": rate_hz,
           "gyroscope_noise_density": noise.gyro_noise_density, "gyroscope_random_walk": noise.gyro_random_walk,
           "accelerometer_noise_density": noise.accel_noise_density,
           "accelerometer_random_walk": noise.accel_random_walk}
    _yaml(mav0 / "imu0" / "sensor.yaml", doc)
    _yaml(mav0 / "state_groundtruth_estimate0" / "sensor.yaml",
          {"sensor_type": "visual-inertial", "comment": "VI3 exact simulated body state (no estimation).",
           "T_BS": _IDENTITY_T_BS})
    (mav0 / "body.yaml").write_text("comment: VI3 simulated drone (EuRoC body frame = IMU frame)\n")


def write_depth_yaml(mav0: Path, K: np.ndarray) -> None:
    """depth0/sensor.yaml: how to read the depth PNGs (scale, the undistorted pinhole K they belong to)."""
    _yaml(mav0 / "depth0" / "sensor.yaml",
          {"sensor_type": "depth", "comment": "Exact ground-truth z-depth of the undistorted cam0 image "
           f"(pinhole K below), uint16 PNG, metres x {DEPTH_SCALE:g}, 0 = no depth.",
           "depth_scale": DEPTH_SCALE, "camera": "cam0", "undistorted_K": np.asarray(K).reshape(-1).tolist()})


def _yaml(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))


def write_image(folder: Path, ns: int, image: np.ndarray) -> None:
    """One mono8 frame as ``<ns>.png``."""
    # Huffman-only deflate: lossless like any PNG, ~2x faster to write than zlib level 1 on textured frames.
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    if not cv2.imwrite(str(folder / f"{int(ns)}.png"), image, params):
        raise DataError(f"{folder}: could not write {int(ns)}.png")


def write_depth(folder: Path, ns: int, depth: np.ndarray) -> None:
    """One depth map [H,W] float32 (m, NaN invalid) as a 16-bit ``<ns>.png``."""
    q = np.rint(np.nan_to_num(depth, nan=0.0) * DEPTH_SCALE)
    q[(q > 65535) | (q < 0)] = 0
    if not cv2.imwrite(str(folder / f"{int(ns)}.png"), q.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise DataError(f"{folder}: could not write {int(ns)}.png")
