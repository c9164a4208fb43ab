"""EuRoC ASL folders (``mav0/``): reading and writing, byte-compatible with the layout EuRoC ships.

Layout: ``cam0/data/<ns>.png`` (mono8) + ``cam0/data.csv`` + ``cam0/sensor.yaml``, ``imu0/data.csv`` +
``imu0/sensor.yaml``, ``state_groundtruth_estimate0/data.csv`` (p, q as w x y z, v, gyro bias, accel bias, all
in EuRoC's column order) + ``sensor.yaml``, ``body.yaml``.

Extra folder (generated sequences only), ``depth0/``: exact ground-truth z-depth of the *undistorted* cam0
image (pinhole intrinsics ``calib.undistorter().K``), one 16-bit PNG per cam0 frame, ``data/<ns>.png``,
value = depth in metres x ``DEPTH_SCALE`` (0.25 mm steps, up to 16.38 m), 0 = no depth; listed in
``depth0/data.csv``; ``depth0/sensor.yaml`` restates this.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from vi3_core import so3
from vi3_core.dataset.calib import CameraCalib, load_calib, write_euroc_sensor_yaml
from vi3_core.dataset.sequence import GroundTruthTrack, Sequence
from vi3_core.errors import DataError
from vi3_core.sim.imu import ImuNoise
from vi3_core.types import ImuSamples

DEPTH_SCALE = 4000.0

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


def read_csv(path: Path, *, columns: int, first: str = "#timestamp") -> tuple[np.ndarray, np.ndarray]:
    """An EuRoC csv: ([R] int64 ns, [R, columns-1] str cells); checks the header names ``columns`` columns."""
    if not path.is_file():
        raise DataError(f"{path}: missing")
    with path.open() as f:
        header = f.readline().strip()
    names = [h.strip() for h in header.split(",")]
    if len(names) != columns or not names[0].startswith(first):
        raise DataError(f"{path}: header {header!r} is not EuRoC's: expected {columns} comma-separated columns "
                        f"starting with {first!r}")
    rows = np.loadtxt(path, delimiter=",", skiprows=1, comments=None, dtype=str, ndmin=2)
    if rows.size and rows.shape[1] != columns:
        raise DataError(f"{path}: rows have {rows.shape[1]} columns, the header {columns}")
    rows = np.char.strip(rows.reshape(-1, columns))
    try:
        ns = rows[:, 0].astype(np.int64)
    except ValueError as err:
        raise DataError(f"{path}: timestamp column is not integer nanoseconds ({err})") from None
    return ns, rows[:, 1:]


def _floats(cells: np.ndarray, path: Path) -> np.ndarray:
    try:
        return cells.astype(np.float64)
    except ValueError as err:
        raise DataError(f"{path}: non-numeric value ({err})") from None


def _read_png(path: Path, flags: int) -> np.ndarray:
    img = cv2.imread(str(path), flags)
    if img is None:
        raise DataError(f"{path}: missing or not a readable PNG")
    return img


def read_imu(mav0: Path) -> tuple[np.ndarray, ImuSamples]:
    """imu0/data.csv -> (ns [M] int64, ImuSamples)."""
    path = mav0 / "imu0" / "data.csv"
    ns, cells = read_csv(path, columns=7)
    vals = _floats(cells, path)
    return ns, ImuSamples(ns * 1e-9, vals[:, :3], vals[:, 3:])


def read_groundtruth(mav0: Path) -> GroundTruthTrack | None:
    """state_groundtruth_estimate0/data.csv -> track (None when the folder is absent)."""
    path = mav0 / "state_groundtruth_estimate0" / "data.csv"
    if not path.parent.is_dir():
        return None
    ns, cells = read_csv(path, columns=17)
    vals = _floats(cells, path)
    q_xyzw = vals[:, [4, 5, 6, 3]]
    T = so3.make_T(so3.quat_to_R(q_xyzw), vals[:, :3])
    return GroundTruthTrack(ns * 1e-9, T, v_WB=vals[:, 7:10], bg=vals[:, 10:13], ba=vals[:, 13:16], t_ns=ns)


def read_asl(path, *, camera: str = "cam0") -> Sequence:
    """Open an ASL folder (``mav0`` or its parent) as a Sequence; images and depth load lazily."""
    mav0 = find_mav0(path)
    cam_dir = mav0 / camera
    calib = load_calib(cam_dir / "sensor.yaml")
    ns, cells = read_csv(cam_dir / "data.csv", columns=2)
    files = [cam_dir / "data" / f for f in cells[:, 0]]
    order = np.argsort(ns, kind="stable")
    ns, files = ns[order], [files[i] for i in order]
    imu_ns, imu = read_imu(mav0)
    depth_dir = mav0 / "depth0"
    load_depth = None
    if (depth_dir / "data.csv").is_file():
        d_ns, d_cells = read_csv(depth_dir / "data.csv", columns=2)
        by_ns = dict(zip(d_ns.tolist(), d_cells[:, 0].tolist()))
        depth_files = [depth_dir / "data" / by_ns[k] if k in by_ns else None for k in ns.tolist()]

        def load_depth(i: int) -> np.ndarray | None:
            if depth_files[i] is None:
                return None
            raw = _read_png(depth_files[i], cv2.IMREAD_UNCHANGED).astype(np.float32)
            raw[raw == 0] = np.nan
            return raw / np.float32(DEPTH_SCALE)

    def load_image(i: int) -> np.ndarray:
        img = _read_png(files[i], cv2.IMREAD_UNCHANGED)
        return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)

    return Sequence(name=mav0.resolve().parent.name, stamps=ns * 1e-9, imu=imu, calib=calib,
                    gt=read_groundtruth(mav0), load_image=load_image, load_depth=load_depth, stamps_ns=ns,
                    imu_ns=imu_ns)


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
