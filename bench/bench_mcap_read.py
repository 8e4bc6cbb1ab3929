"""Read throughput and peak memory of ``McapLog`` on a multi-GB MCAP, against bare ``mcap``.

Goal: reading a multi-GB MCAP of images and point clouds should run within 1.3x of the
``mcap`` library's own decode of every message, and its peak memory should not grow with the
log's length. This benchmark checks both in one run and prints the ratios; it never fails.

1. Writes a synthetic drive with mapkit's ``McapWriter``: 640x480 rgb8 images at 10 Hz (smooth
   gradients plus sensor noise, so that chunks compress like camera data), a 64-beam LiDAR
   PointCloud2 of 60-120k points (x, y, z, intensity, time, ring) at 10 Hz, GPS at 5 Hz and IMU at
   100 Hz; its length is chosen (from a short calibration log) to make a file of ``--gb`` GB, and
   a second log a quarter as long is written for the memory check.
2. Reads each log once to warm the page cache, so that every mode reads from memory alike.
3. Times each reading mode in fresh processes (``--rounds`` of them, interleaved with the other
   modes, each keeping the best of ``--repeat`` reads), which also gives their peak RSS:
   (a) ``mcap-decoded``: ``make_reader(...).iter_decoded_messages()`` with ``mcap_ros2``'s decoder,
       the baseline of the 1.3x goal;
   (a') ``mcap-decoded+crc``: (a) with ``validate_crcs=True``, as ``McapLog`` reads (context);
   (b) ``mcap-raw``: ``iter_messages()`` without decoding, a lower bound for context;
   (c) ``mapkit``: ``McapLog(path).messages()``, touching every image and point array.

Run from the repository root::

    python bench/bench_mcap_read.py            # 2 GB log (and a 0.5 GB one)
    python bench/bench_mcap_read.py --quick    # 0.2 GB smoke run
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.common import best_of, peak_rss_mb_of, report, self_peak_rss_mb  # noqa: E402 (after sys.path points at this checkout)

# numpy, mcap and mapkit are imported inside functions, and the logs are written in a child
# process: ``peak_rss_mb_of`` reports the larger of the child's peak and the *parent's* (Linux
# carries ``ru_maxrss`` over fork + exec), so the measuring process must stay small. Each child
# also records its own high-water mark (VmHWM, per address space) as a cross-check.

GB = 1e9
#: the goals: mapkit within 1.3x of bare mcap decoding; peak memory flat in log length
THROUGHPUT_GOAL = 1.3
MEMORY_GOAL = 1.10  # peak RSS of the full log over that of the quarter log ("about 1.0")


# --- synthetic drive ------------------------------------------------------------------------------


@dataclass(frozen=True)
class DriveSpec:
    """What the synthetic log holds; rates and sizes of a typical car sensor set."""

    image_height: int = 480
    image_width: int = 640
    image_hz: float = 10.0
    image_noise_sigma: float = 2.0  # digital numbers; a camera's read + shot noise
    lidar_hz: float = 10.0
    lidar_beams: int = 64
    lidar_columns: int = 2048  # 64 x 2048 = 131k directions (Ouster OS1-64 at 10 Hz)
    lidar_points_min: int = 60_000
    lidar_points_max: int = 120_000
    lidar_range_sigma_m: float = 0.02
    gps_hz: float = 5.0
    imu_hz: float = 100.0
    speed_m_s: float = 10.0
    turn_radius_m: float = 400.0
    seed: int = 7

    TOPICS = {"image": "/camera/image_raw", "lidar": "/lidar/points", "gps": "/gps/fix", "imu": "/imu/data"}


class _SyntheticSensors:
    """A few base images and scans made once, varied cheaply per frame (roll + fresh-offset noise)."""

    N_BASES = 4

    def __init__(self, spec: DriveSpec):
        import numpy as np

        self.np = np
        self.spec = spec
        rng = np.random.default_rng(spec.seed)
        h, w = spec.image_height, spec.image_width
        self.bases = [self._base_image(h, w, k, rng) for k in range(self.N_BASES)]
        # one bank of noise, read at a different offset per frame: no two frames share a byte run
        n_px = h * w * 3
        noise = np.clip(np.rint(rng.normal(0.0, spec.image_noise_sigma, 3 * n_px)), -8, 8)
        self.image_noise = noise.astype(np.int8).view(np.uint8)  # added modulo 256 = signed add
        self.scans = [self._base_scan(k, rng) for k in range(self.N_BASES)]
        n_dirs = spec.lidar_beams * spec.lidar_columns
        self.range_noise = rng.normal(0.0, spec.lidar_range_sigma_m, 3 * n_dirs).astype(np.float32)
        self.intensity_noise = rng.normal(0.0, 3.0, 3 * n_dirs).astype(np.float32)
        self.keep_noise = rng.random(3 * n_dirs, dtype=np.float32)
        self.rng = rng

    @staticmethod
    def _base_image(h: int, w: int, k: int, rng):
        """Sky gradient, a row of facades, a road: smooth, with a few hard edges, in [16, 239]."""
        import numpy as np

        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        img = np.empty((h, w, 3), np.float32)
        horizon = h * (0.35 + 0.05 * k)
        sky = yy < horizon
        img[..., 0] = np.where(sky, 120 + 60 * yy / h, 90 + 50 * yy / h)
        img[..., 1] = np.where(sky, 150 + 50 * yy / h, 90 + 45 * yy / h)
        img[..., 2] = np.where(sky, 220 - 30 * yy / h, 85 + 40 * yy / h)
        # facades: vertical bands of smooth colour between the horizon and the road
        facade = (yy >= horizon) & (yy < h * 0.62)
        band = np.sin(xx / w * (6 + k) * np.pi + k) * 0.5 + 0.5
        shade = 40 * np.cos(yy / h * 9 + xx / w * 3)
        for c, (lo, hi) in enumerate(((70, 190), (60, 160), (50, 140))):
            img[..., c] = np.where(facade, lo + (hi - lo) * band + shade, img[..., c])
        # a few dark windows (hard edges compress differently from gradients)
        win = facade & ((xx.astype(np.int32) // 23) % 3 == 0) & ((yy.astype(np.int32) // 17) % 2 == 0)
        img[win] *= 0.45
        img += rng.normal(0, 4, (1, w, 3)).astype(np.float32)  # column fixed-pattern noise
        return np.clip(img, 16, 239).astype(np.uint8)

    def _base_scan(self, k: int, rng) -> dict:
        """Directions (column-major, firing order) and ranges of a street canyon with a ground plane."""
        np = self.np
        spec = self.spec
        beams, cols = spec.lidar_beams, spec.lidar_columns
        elev = np.deg2rad(np.linspace(-22.5, 22.5, beams))  # OS1-64 vertical field of view
        az = np.linspace(0.0, 2 * np.pi, cols, endpoint=False) + 0.3 * k
        el_g, az_g = np.meshgrid(elev, az)  # (cols, beams): column-major, a firing at a time
        dirs = np.stack([np.cos(el_g) * np.cos(az_g), np.cos(el_g) * np.sin(az_g), np.sin(el_g)], -1)
        sensor_height = 1.8
        wall = 9 + 5 * np.maximum(np.abs(np.sin(az_g)), 1e-3) ** -0.5 + 2 * np.sin(7 * az_g + k)  # facades, open ahead
        wall = np.minimum(wall, 90.0)
        r_wall = wall / np.cos(el_g)
        r_ground = np.where(el_g < 0, sensor_height / np.sin(-np.minimum(el_g, -1e-3)), np.inf)
        r = np.minimum(r_wall, r_ground)
        z_hit = sensor_height + r * np.sin(el_g)
        valid = (z_hit < 14.0 + 6 * np.sin(3 * az_g + k)) & (r < 120.0)  # above the roofs: sky
        intensity = np.clip(30 + 40 * np.sin(az_g * 13 + el_g * 40) ** 2 + 200 / (1 + r), 0, 255)
        return {
            "dirs": dirs.reshape(-1, 3).astype(np.float32),
            "range": r.reshape(-1).astype(np.float32),
            "valid": valid.reshape(-1),
            "intensity": intensity.reshape(-1).astype(np.float32),
            "ring": np.tile(np.arange(beams, dtype=np.uint16), cols),
            "time": np.repeat(np.arange(cols, dtype=np.float32) / (cols * spec.lidar_hz), beams),
        }

    def image(self, i: int):
        np = self.np
        base = self.bases[i % self.N_BASES]
        img = np.roll(base, (3 * i) % base.shape[1], axis=1)  # the view pans
        n = img.size
        off = int(self.rng.integers(0, self.image_noise.size - n))
        flat = img.reshape(-1)
        np.add(flat, self.image_noise[off : off + n], out=flat)
        return img

    def scan(self, i: int):
        """(xyz, intensity, time, ring) of one sweep with 60-120k valid points."""
        np = self.np
        spec = self.spec
        base = self.scans[i % self.N_BASES]
        n = base["range"].size
        shift = ((5 * i) % spec.lidar_columns) * spec.lidar_beams  # the car turns a little
        off = int(self.rng.integers(0, self.range_noise.size - n))
        r = np.roll(base["range"], shift) + self.range_noise[off : off + n]
        valid = np.roll(base["valid"], shift)
        want = int(self.rng.integers(spec.lidar_points_min, spec.lidar_points_max + 1))
        keep = valid & (self.keep_noise[off : off + n] < want / max(1, int(valid.sum())))
        xyz = base["dirs"][keep] * r[keep, None]
        intensity = np.roll(base["intensity"], shift)[keep] + self.intensity_noise[off : off + n][keep]
        return xyz, np.clip(intensity, 0, 255), base["time"][keep], base["ring"][keep]


def write_drive(
    path: Path, duration_s: float, spec: DriveSpec, compression: str = "zstd", progress: bool = True
) -> Path:
    """Write ``duration_s`` seconds of the synthetic drive to ``path`` (an MCAP) and return it."""
    import numpy as np
    from tqdm import tqdm

    from mapkit.core.types import CameraFrame, GpsFix, ImuSample, LidarScan
    from mapkit.io.mcap_log import McapWriter

    sensors = _SyntheticSensors(spec)
    rng = np.random.default_rng(spec.seed + 1)
    topics = DriveSpec.TOPICS
    imu_dt_ns = int(round(1e9 / spec.imu_hz))
    per_image = int(round(spec.imu_hz / spec.image_hz))
    per_scan = int(round(spec.imu_hz / spec.lidar_hz))
    per_gps = int(round(spec.imu_hz / spec.gps_hz))
    n_ticks = int(math.ceil(duration_s * spec.imu_hz))
    t0_ns = 1_700_000_000 * 10**9
    lat0, lon0, earth_r = 48.137, 11.575, 6_378_137.0
    yaw_rate = spec.speed_m_s / spec.turn_radius_m
    cov_gps = np.diag([0.5, 0.5, 1.5]) ** 2

    with McapWriter(path, compression=compression) as writer:
        writer.add_metadata("mapkit-bench", {**asdict(spec), "duration_s": duration_s})
        bar = tqdm(
            total=n_ticks / spec.imu_hz,
            unit="log-s",
            desc=f"writing {path.name}",
            disable=not progress,
            file=sys.stderr,
            bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} {unit} [{elapsed}<{remaining}]",
        )
        for k in range(n_ticks):
            t_ns = t0_ns + k * imu_dt_ns
            t_s = k / spec.imu_hz
            yaw = yaw_rate * t_s
            q = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
            gyro = np.array([0.0, 0.0, yaw_rate]) + rng.normal(0, 0.002, 3)
            accel = np.array([0.0, spec.speed_m_s * yaw_rate, 9.81]) + rng.normal(0, 0.05, 3)
            writer.write(topics["imu"], ImuSample(t_ns, "imu", gyro, accel, orientation_quat_wxyz=q))
            if k % per_image == 0:
                i = k // per_image
                writer.write(topics["image"], CameraFrame(t_ns, "camera", sensors.image(i), encoding="rgb8"))
            if k % per_scan == per_scan // 2:
                xyz, intensity, point_time, ring = sensors.scan(k // per_scan)
                writer.write(
                    topics["lidar"],
                    LidarScan(t_ns, "lidar", xyz, intensity=intensity, point_time_s=point_time, ring=ring),
                )
            if k % per_gps == 0:
                east = spec.turn_radius_m * math.sin(yaw)
                north = spec.turn_radius_m * (1 - math.cos(yaw))
                lat = lat0 + math.degrees(north / earth_r) + rng.normal(0, 3e-6)
                lon = lon0 + math.degrees(east / (earth_r * math.cos(math.radians(lat0)))) + rng.normal(0, 3e-6)
                writer.write(
                    topics["gps"], GpsFix(t_ns, lat, lon, 520.0 + rng.normal(0, 0.5), covariance_enu_m2=cov_gps)
                )
            if k % 10 == 9:
                bar.update(10 / spec.imu_hz)
        bar.close()
    return path


def log_name(gb: float, compression: str, spec: DriveSpec) -> str:
    """Logs are named from what made them, so ``--keep`` + ``--workdir`` reuses them."""
    return f"synthetic-{gb:g}gb-{compression}-seed{spec.seed}.mcap"


def make_logs(workdir: Path, gb: float, compression: str, spec: DriveSpec, overwrite: bool = False) -> dict:
    """Paths and write times of the full-size and quarter-length logs (reused if already there)."""
    full = workdir / log_name(gb, compression, spec)
    quarter = workdir / log_name(gb / 4, compression, spec)
    info = {"full": {"path": str(full)}, "quarter": {"path": str(quarter)}}
    if full.is_file() and quarter.is_file() and not overwrite:
        print(f"reusing {full.name} and {quarter.name} in {workdir}", file=sys.stderr)
        for v in info.values():
            v["write_s"] = float("nan")
        return info
    # bytes per second of log depend on content and compression: measure them on a short log
    calib_s = 3.0
    calib = write_drive(workdir / "calibration.mcap", calib_s, spec, compression, progress=False)
    bytes_per_s = calib.stat().st_size / calib_s
    calib.unlink()
    duration_s = gb * GB / bytes_per_s
    print(
        f"calibration: {bytes_per_s / 1e6:.1f} MB per second of log -> {duration_s:.0f} s of log for {gb:g} GB",
        file=sys.stderr,
    )
    for key, seconds in (("full", duration_s), ("quarter", duration_s / 4)):
        t0 = time.perf_counter()
        write_drive(Path(info[key]["path"]), seconds, spec, compression)
        info[key]["write_s"] = time.perf_counter() - t0
        info[key]["duration_s"] = seconds
    return info


def make_logs_in_child(workdir: Path, gb: float, compression: str, overwrite: bool) -> dict:
    """``make_logs`` in a fresh process (its stderr, with the progress bars, goes to ours)."""
    out = workdir / "logs.json"
    code = (
        f"import sys, json; sys.path.insert(0, {str(ROOT)!r})\n"
        f"from pathlib import Path\n"
        f"from bench.bench_mcap_read import make_logs, DriveSpec\n"
        f"info = make_logs(Path({str(workdir)!r}), {gb!r}, {compression!r}, DriveSpec(), {overwrite!r})\n"
        f"Path({str(out)!r}).write_text(json.dumps(info))"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    info = json.loads(out.read_text())
    out.unlink()
    return info


# --- reading modes (each runs in a fresh process) -------------------------------------------------


def read_mcap_raw(path: str) -> tuple[int, int]:
    """(b) bare ``mcap``: every message record, payload left as CDR bytes."""
    from mcap.reader import make_reader

    n = nbytes = 0
    with open(path, "rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages():
            n += 1
            nbytes += len(message.data)
    return n, nbytes


def read_mcap_decoded(path: str, validate_crcs: bool = False) -> tuple[int, int]:
    """(a) bare ``mcap`` + ``mcap_ros2``: the library's own decode of every message (the baseline)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    n = nbytes = 0
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=validate_crcs, decoder_factories=[DecoderFactory()])
        for _schema, _channel, _message, decoded in reader.iter_decoded_messages():
            n += 1
            data = getattr(decoded, "data", None)  # Image and PointCloud2 payloads
            if data is not None:
                nbytes += len(data)
    return n, nbytes


def read_mcap_decoded_crc(path: str) -> tuple[int, int]:
    """(a') as (a), checking each chunk's CRC as ``McapLog`` does: the like-for-like comparison."""
    return read_mcap_decoded(path, validate_crcs=True)


def read_mapkit(path: str, validate_crcs: bool = True) -> tuple[int, int]:
    """(c) ``McapLog.messages()``: records with their arrays materialised (lazy decoding can't cheat)."""
    from mapkit.core.types import CameraFrame, LidarScan
    from mapkit.io.mcap_log import McapLog

    n = nbytes = 0
    with McapLog(path, validate_crcs=validate_crcs) as log:
        for msg in log.messages():
            n += 1
            rec = msg.record
            if isinstance(rec, CameraFrame):
                nbytes += rec.image.shape[0] * rec.image.strides[0]
            elif isinstance(rec, LidarScan):
                nbytes += rec.points_xyz.shape[0] * rec.points_xyz.strides[0]
    return n, nbytes


def read_mapkit_nocrc(path: str) -> tuple[int, int]:
    """(c') as (c) without chunk CRC checks: like for like with (a), which checks none."""
    return read_mapkit(path, validate_crcs=False)


def open_mcap(path: str) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory  # noqa: F401 - imported by the decoding mode

    with open(path, "rb") as f:
        make_reader(f).get_summary()


def open_mapkit(path: str) -> None:
    from mapkit.io.mcap_log import McapLog

    with McapLog(path) as log:
        log.streams()


#: mode -> (reader, what to do for the "imports and open only" baseline of memory)
MODES: dict[str, tuple[Callable[[str], tuple[int, int]], Callable[[str], None]]] = {
    "mcap-raw": (read_mcap_raw, open_mcap),
    "mcap-decoded": (read_mcap_decoded, open_mcap),
    "mcap-decoded+crc": (read_mcap_decoded_crc, open_mcap),
    "mapkit": (read_mapkit, open_mapkit),
    "mapkit-nocrc": (read_mapkit_nocrc, open_mapkit),
}
BASELINE = "mcap-decoded"


def _own_peak_rss_mb() -> float:
    """High-water RSS of this process's address space (unlike ru_maxrss, not inherited at exec)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def run_mode(mode: str, path: str, repeat: int, out_json: str) -> None:
    """Child-process entry: time ``repeat`` reads of ``path`` (0: only import and open it)."""
    read, open_only = MODES[mode]
    result: dict = {"mode": mode, "cpu_s": []}
    open_only(path)  # imports happen here, not inside the first timed read
    if repeat > 0:

        def once() -> None:
            c0 = time.process_time()
            result["messages"], result["payload_bytes"] = read(path)
            result["cpu_s"].append(time.process_time() - c0)

        result["wall_s"] = best_of(once, repeat)
        result["cpu_s"] = min(result["cpu_s"])
    result["vm_hwm_mb"] = _own_peak_rss_mb()
    Path(out_json).write_text(json.dumps(result))


def measure(mode: str, path: Path, repeat: int, scratch: Path) -> dict:
    """Run one mode in a fresh process; its timings plus that process's peak RSS."""
    out = scratch / f"result-{mode}-{path.stem}-{repeat}.json"
    code = (
        f"import sys; sys.path.insert(0, {str(ROOT)!r})\n"
        f"from bench.bench_mcap_read import run_mode\n"
        f"run_mode({mode!r}, {str(path)!r}, {repeat}, {str(out)!r})"
    )
    rss = peak_rss_mb_of(code)
    result = json.loads(out.read_text())
    out.unlink()
    result["peak_rss_mb"] = rss
    return result


def warm_page_cache(paths: list[Path]) -> None:
    from tqdm import tqdm

    total = sum(p.stat().st_size for p in paths)
    buf = bytearray(1 << 20)  # small: this process's peak RSS is the floor of every measurement
    with tqdm(total=total, unit="B", unit_scale=True, desc="warm-up read (page cache)", file=sys.stderr) as bar:
        for p in paths:
            with open(p, "rb", buffering=0) as f:
                while n := f.readinto(buf):
                    bar.update(n)


# --- the benchmark --------------------------------------------------------------------------------


def run_benchmark(
    gb: float,
    repeat: int,
    rounds: int,
    compression: str,
    workdir: Path | None,
    keep: bool,
    overwrite: bool = False,
    spec: DriveSpec = DriveSpec(),
) -> dict:
    from tqdm import tqdm

    own_dir = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="mapkit-bench-mcap-", dir="/tmp")) if own_dir else workdir
    workdir.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix="results-", dir=workdir))
    try:
        logs = make_logs_in_child(workdir, gb, compression, overwrite)
        paths = {k: Path(v["path"]) for k, v in logs.items()}
        warm_page_cache(list(paths.values()))

        # modes alternate within each round (reversed every other round) so that load from other
        # processes on the machine falls on all of them alike; the best round counts, memory the worst
        steps = [(mode, log, 0) for log in paths for mode in MODES]  # imports-and-open baselines
        for rnd in range(rounds):
            order = list(MODES) if rnd % 2 == 0 else list(reversed(MODES))
            steps += [(mode, log, repeat) for log in paths for mode in order]
        results: dict[tuple[str, str, int], dict] = {}
        load_before = os.getloadavg()[0]
        with tqdm(steps, desc="measuring", file=sys.stderr) as bar:
            for mode, log, rep in bar:
                bar.set_postfix_str(f"{mode} on {log} log, {'open only' if rep == 0 else f'best of {rep}'}")
                r = measure(mode, paths[log], rep, scratch)
                prev = results.setdefault((mode, log, rep), r)
                for key, pick in (("wall_s", min), ("cpu_s", min), ("peak_rss_mb", max), ("vm_hwm_mb", max)):
                    if key in r:
                        prev[key] = pick(prev[key], r[key])
        parent_rss = self_peak_rss_mb()
        load_after = os.getloadavg()[0]

        rows = []
        for log, path in paths.items():
            size = path.stat().st_size
            base_wall = results[BASELINE, log, repeat]["wall_s"]
            raw_wall = results["mcap-raw", log, repeat]["wall_s"]
            for mode in MODES:
                r = results[mode, log, repeat]
                rows.append(
                    {
                        "mode": mode,
                        "log": log,
                        "file_GB": size / GB,
                        "messages": r["messages"],
                        "wall_s": r["wall_s"],
                        "cpu_s": r["cpu_s"],
                        "file_MB_per_s": size / 1e6 / r["wall_s"],
                        "msgs_per_s": r["messages"] / r["wall_s"],
                        "x_mcap_decoded": r["wall_s"] / base_wall,
                        "x_mcap_raw": r["wall_s"] / raw_wall,
                        "peak_rss_MB": r["peak_rss_mb"],
                        "own_hwm_MB": r["vm_hwm_mb"],
                        "open_rss_MB": results[mode, log, 0]["peak_rss_mb"],
                    }
                )
        gen_rows = [
            {
                "log": log,
                "file_GB": paths[log].stat().st_size / GB,
                "messages": results["mcap-raw", log, repeat]["messages"],
                "payload_GB": results["mcap-raw", log, repeat]["payload_bytes"] / GB,
                "compressed_over_raw": paths[log].stat().st_size / results["mcap-raw", log, repeat]["payload_bytes"],
                "log_s": logs[log].get("duration_s", float("nan")),
                "write_s": logs[log]["write_s"],
            }
            for log in paths
        ]
        return {
            "rows": rows,
            "generation": gen_rows,
            "workdir": str(workdir),
            "compression": compression,
            "repeat": repeat,
            "rounds": rounds,
            "parent_rss_mb": parent_rss,
            "load_avg_1min": (load_before, load_after),
        }
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        if not keep:
            if own_dir:
                shutil.rmtree(workdir, ignore_errors=True)
            else:
                for name in (log_name(gb, compression, spec), log_name(gb / 4, compression, spec)):
                    (workdir / name).unlink(missing_ok=True)


def summarise(out: dict) -> None:
    rows = out["rows"]
    by = {(r["mode"], r["log"]): r for r in rows}
    # like for like: mapkit without CRC checks against bare mcap (which checks none), and mapkit's
    # default (CRCs checked) against bare mcap with CRCs checked
    full_ratio = by["mapkit-nocrc", "full"]["x_mcap_decoded"]
    cpu_ratio = by["mapkit-nocrc", "full"]["cpu_s"] / by[BASELINE, "full"]["cpu_s"]
    crc_ratio = by["mapkit", "full"]["wall_s"] / by["mcap-decoded+crc", "full"]["wall_s"]
    mem = {m: by[m, "full"]["peak_rss_MB"] / by[m, "quarter"]["peak_rss_MB"] for m in MODES}
    mk_full, mk_quarter = by["mapkit", "full"], by["mapkit", "quarter"]
    delta_full = mk_full["peak_rss_MB"] - mk_full["open_rss_MB"]
    delta_quarter = mk_quarter["peak_rss_MB"] - mk_quarter["open_rss_MB"]

    report(
        "generated logs",
        out["generation"],
        f"compression {out['compression']}; payload = CDR bytes of all messages; write_s includes generating content "
        f"(nan: reused from --workdir)",
    )
    note = "\n".join(
        [
            f"Each mode runs in {out['rounds']} fresh processes interleaved with the other modes, each timing "
            f"{out['repeat']} reads; the best read is shown, and the highest peak RSS. "
            "The page cache was warmed by one read of both logs first, so every mode reads from memory. "
            "open_rss_MB: a process importing and opening the log without reading it. "
            f"peak_rss_MB is bench.common.peak_rss_mb_of, floored by the measuring "
            f"process's own peak ({out['parent_rss_mb']:.0f} MB); own_hwm_MB is the child's VmHWM, a cross-check.",
            f"Throughput, like for like: mapkit (no CRC) / mcap-decoded = {full_ratio:.2f}x wall "
            f"({cpu_ratio:.2f}x CPU) on the full log, "
            f"{by['mapkit-nocrc', 'quarter']['x_mcap_decoded']:.2f}x on the quarter log; "
            f"mapkit (default, CRCs checked) / mcap-decoded+crc = {crc_ratio:.2f}x; "
            f"mapkit (default) / mcap-decoded = {by['mapkit', 'full']['x_mcap_decoded']:.2f}x; "
            f"mapkit / mcap-raw = {by['mapkit', 'full']['x_mcap_raw']:.2f}x. "
            f"Goal <= {THROUGHPUT_GOAL}x: {'MET' if max(full_ratio, crc_ratio) <= THROUGHPUT_GOAL else 'NOT MET'} "
            f"(the larger of the two like-for-like ratios).",
            f"Memory: peak RSS full / quarter log = {mem['mapkit']:.3f} for mapkit "
            f"({mk_full['peak_rss_MB']:.0f} vs {mk_quarter['peak_rss_MB']:.0f} MB; above open: {delta_full:.0f} vs "
            f"{delta_quarter:.0f} MB), {mem['mcap-decoded']:.3f} for mcap-decoded, {mem['mcap-raw']:.3f} for mcap-raw. "
            f"Goal <= {MEMORY_GOAL} (flat in log length): {'MET' if mem['mapkit'] <= MEMORY_GOAL else 'NOT MET'}.",
        ]
    )
    # a single-threaded read that waits for a CPU shows wall > CPU: then CPU ratios are the better guide
    busy = [f"{r['mode']}/{r['log']}" for r in rows if r["wall_s"] > 1.10 * r["cpu_s"]]
    load = out["load_avg_1min"]
    note += (
        f"\nMachine load (1-min average) {load[0]:.1f} before and {load[1]:.1f} after the reads on "
        f"{os.cpu_count()} CPUs."
    )
    if busy:
        note += (
            f" Wall time exceeded CPU time by >10% for {', '.join(busy)}: other processes competed for "
            f"the CPUs, so compare the CPU ratio ({cpu_ratio:.2f}x) rather than the wall ratio."
        )
    report("MCAP read: mapkit vs bare mcap", rows, note)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--gb", type=float, default=2.0, help="size of the full log in GB (10^9 bytes); default 2.0")
    p.add_argument("--quick", action="store_true", help="smoke run: a 0.2 GB log (overrides --gb)")
    p.add_argument("--repeat", type=int, default=2, help="reads per process, the best is kept; default 2")
    p.add_argument(
        "--rounds", type=int, default=2, help="fresh processes per mode, interleaved with the other modes; default 2"
    )
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunk compression")
    p.add_argument(
        "--workdir", type=Path, default=None, help="where the logs are written (default: a new folder under /tmp)"
    )
    p.add_argument("--keep", action="store_true", help="keep the logs (with --workdir, later runs reuse them)")
    p.add_argument("--overwrite", action="store_true", help="rewrite logs already in --workdir")
    args = p.parse_args(argv)
    gb = 0.2 if args.quick else args.gb
    out = run_benchmark(gb, args.repeat, args.rounds, args.compression, args.workdir, args.keep, args.overwrite)
    summarise(out)
    if args.keep:
        print(f"\nlogs kept in {out['workdir']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
