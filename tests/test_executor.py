"""The executor interface: order, errors naming their item, shared state shipped once per worker,
lazy consumption; serial == process pool on real mapkit work (semi-dense keyframes, ICP of submap
pairs); and the issue's test: the VLAD index of the synthetic ``tiny`` town built in this process
and on a local Ray instance holds the same vectors, bit for bit."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from test_align import street
from test_semidense import K_SYN, ROOM_CFG, room  # noqa: F401 - the rendered room, a module fixture used below

from mapkit.core.errors import ConfigError, InputError, InputWarning, MapkitError
from mapkit.core.executor import (
    SERIAL,
    ProcessExecutor,
    SerialExecutor,
    TaskError,
    get_executor,
    make_executor,
    use_executor,
)
from mapkit.mapping.semidense import build_semidense_map
from mapkit.multisession.align import AlignConfig, _register_task
from mapkit.multisession.submaps import SubmapClouds
from mapkit.retrieval.index_vlad import read_image
from mapkit.synth import session_logs

# --------------------------------------------------------------------------- task functions (importable by workers)


def slow_square(x: int) -> int:
    time.sleep(0.03 * (x % 3 == 0))  # every third item is slower: workers finish out of order
    return x * x


def thread_env(_: int) -> tuple[int, str | None]:
    time.sleep(0.05)  # long enough that the pool starts its second worker
    return os.getpid(), os.environ.get("OMP_NUM_THREADS")


def inverse(x: float) -> float:
    return 1.0 / x


_UNPICKLED = 0  # per process: how many times a CountedShared arrived here


class CountedShared:
    """Shared state that counts its arrivals in a process."""

    def __init__(self, values: np.ndarray):
        self.values = values

    def __setstate__(self, state: dict) -> None:
        global _UNPICKLED
        _UNPICKLED += 1
        self.__dict__.update(state)


def lookup(shared: CountedShared, i: int) -> tuple[float, int, int]:
    return float(shared.values[i]), os.getpid(), _UNPICKLED


def producer(n: int, fail_at: int | None = None, pulled: list | None = None):
    for i in range(n):
        if i == fail_at:
            raise InputError("frames.csv", f"row {i} is broken", field="row")
        if pulled is not None:
            pulled.append(i)
        yield i


EXECUTORS = {
    "serial": lambda: SERIAL,
    "process": lambda: ProcessExecutor(2),
    "kept": lambda: ProcessExecutor(2, keep_pool=True),  # one pool for every map, until closed
}


# --------------------------------------------------------------------------- the contract, local executors


@pytest.mark.parametrize("kind", EXECUTORS)
def test_results_come_back_in_input_order(kind):
    items = list(range(12))
    assert list(EXECUTORS[kind]().map(slow_square, iter(items), chunksize=5)) == [
        x * x for x in items
    ]  # a generator, in chunks
    assert list(EXECUTORS[kind]().map(slow_square, [])) == []


@pytest.mark.parametrize("kind", EXECUTORS)
def test_first_failure_names_its_item_after_the_results_before_it(kind):
    got = []
    with pytest.raises(TaskError) as e:
        for r in EXECUTORS[kind]().map(inverse, [1.0, 2.0, 0.0, 4.0, 0.0], desc="inverse"):
            got.append(r)
    assert got == [1.0, 0.5]
    assert e.value.index == 2 and e.value.item == "0.0"
    assert "inverse failed on item 2 (0.0)" in str(e.value) and "ZeroDivisionError" in str(e.value)
    assert isinstance(e.value.cause, ZeroDivisionError) and isinstance(e.value, MapkitError)


@pytest.mark.parametrize("kind", EXECUTORS)
def test_a_mapkit_error_comes_back_whole_with_a_label(kind, tmp_path):
    missing = tmp_path / "no-such.png"
    with pytest.raises(TaskError) as e:
        list(EXECUTORS[kind]().map(read_image, [str(missing)], label=lambda p: Path(p).name))
    # InputError's __init__ differs from its args: the worker's error is rebuilt, not re-constructed
    assert (
        isinstance(e.value.cause, InputError)
        and e.value.cause.path == missing
        and e.value.cause.what == "cannot read this image"
    )
    assert "(no-such.png)" in str(e.value)
    if kind != "serial":
        assert "read_image" in e.value.remote_traceback


@pytest.mark.parametrize("kind", EXECUTORS)
def test_producer_errors_pass_through_after_the_results_before_them(kind):
    got = []
    with pytest.raises(InputError, match="row 3 is broken"):
        for r in EXECUTORS[kind]().map(slow_square, producer(6, fail_at=3)):
            got.append(r)
    assert got == [0, 1, 4]


@pytest.mark.parametrize("kind", EXECUTORS)
def test_items_are_consumed_lazily(kind):
    pulled: list[int] = []
    results = EXECUTORS[kind]().map(slow_square, producer(1000, pulled=pulled))
    assert next(results) == 0
    bound = 1 if kind == "serial" else 2 * 2  # two chunks (of one item) in flight per worker
    assert len(pulled) <= bound
    results.close()


@pytest.mark.parametrize("kind", EXECUTORS)
def test_shared_state_is_shipped_once_per_worker(kind):
    values = np.arange(20, dtype=np.float64) * 1.5
    out = list(EXECUTORS[kind]().map(lookup, range(20), shared=CountedShared(values)))
    assert [v for v, _, _ in out] == list(values)
    arrivals = {pid: n for _, pid, n in out}
    if kind == "serial":
        assert arrivals == {os.getpid(): _UNPICKLED}  # never pickled in this process
    else:
        assert os.getpid() not in arrivals and set(arrivals.values()) == {1}


def test_a_consumer_done_after_the_last_result_lets_the_pool_close(monkeypatch):
    """zip(items, ex.map(...)) never asks the map for the end: the workers are still let go
    (close), not killed (terminate: SIGTERM, and pycolmap's handler prints a stack trace)."""
    stops: list[bool] = []
    original = ProcessExecutor._stop
    monkeypatch.setattr(
        ProcessExecutor,
        "_stop",
        lambda self, pool, pending, failed: (stops.append(failed), original(self, pool, pending, failed))[1],
    )
    items = list(range(6))
    g = ProcessExecutor(2).map(slow_square, items)
    assert [r for _, r in zip(items, g, strict=False)] == [x * x for x in items]
    g.close()
    g = ProcessExecutor(2).map(slow_square, items)  # abandoned half-way: what is in flight is killed
    next(g)
    g.close()
    assert stops == [False, True]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return Path(f"/proc/{pid}/stat").is_file() and Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"


def test_a_kept_pool_serves_every_map_with_its_own_shared_state_until_closed(tmp_path, monkeypatch):
    """keep_pool: the same workers run map after map, each map's shared state arrives once per worker and
    replaces the last (its temporary file is removed when the map ends); a failed map's workers are killed and
    the next map starts fresh ones; close() lets the workers go."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    ex = ProcessExecutor(2, keep_pool=True)
    try:
        first = list(ex.map(lookup, range(20), shared=CountedShared(np.arange(20.0))))
        second = list(ex.map(lookup, range(20), shared=CountedShared(np.arange(20.0) * -2)))
        assert [v for v, _, _ in first] == list(np.arange(20.0))
        assert [v for v, _, _ in second] == list(np.arange(20.0) * -2)  # the second map's state, not the first's
        pids = {pid for _, pid, _ in first}
        assert {pid for _, pid, _ in second} <= pids and os.getpid() not in pids  # the same workers
        assert {n for _, _, n in first} == {1} and {n for _, _, n in second} == {2}  # once per worker per map
        assert list(tmp_path.iterdir()) == []  # each map's shared file is gone
        assert list(ex.map(slow_square, range(4))) == [0, 1, 4, 9]  # a map without shared state
        with pytest.raises(TaskError):
            list(ex.map(inverse, [1.0, 0.0, 2.0, 3.0, 4.0]))
        assert not any(_alive(p) for p in pids)  # killed with the failed map
        again = list(ex.map(lookup, range(6), shared=CountedShared(np.arange(6.0) + 1)))
        assert [v for v, _, _ in again] == list(np.arange(6.0) + 1)
        fresh = {pid for _, pid, _ in again}
        assert not fresh & pids and all(_alive(p) for p in fresh)
    finally:
        ex.close()
    assert not any(_alive(p) for p in fresh)


_PARENT = """
import json, os, sys, time
sys.path.insert(0, sys.argv[1])
from mapkit.core.executor import ProcessExecutor


def busy(seconds):
    print(json.dumps(os.getpid()), flush=True)  # the worker's pid, as soon as it starts on its item
    time.sleep(seconds)
    return os.getpid()


if __name__ == "__main__":
    for _ in ProcessExecutor(2, keep_pool=sys.argv[2] == "kept").map(busy, [60.0, 60.0]):
        pass
"""


@pytest.mark.parametrize("pool", ["per-map", "kept"])
def test_workers_end_when_their_parent_is_killed(tmp_path, pool):
    """A run killed outright (no pool shutdown reaches its workers) leaves no worker finishing its task and writing
    into the stopped run: each worker ends itself within seconds of its parent."""
    import time

    script = tmp_path / "parent.py"
    script.write_text(_PARENT)
    root = str(Path(__file__).resolve().parents[1])
    parent = subprocess.Popen(
        [sys.executable, str(script), root, pool], stdout=subprocess.PIPE, text=True, cwd=tmp_path
    )
    try:
        workers = [int(parent.stdout.readline()) for _ in range(2)]  # both busy for a minute
        assert all(_alive(p) for p in workers)
        parent.kill()
        parent.wait(timeout=30)
        deadline = time.monotonic() + 15
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(_alive(p) for p in workers)
    finally:
        parent.kill()
        for p in workers if "workers" in locals() else []:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p, signal.SIGKILL)


def test_every_worker_starts_with_one_blas_thread(monkeypatch):
    """Each spawned worker, also those the pool starts as work arrives, has one BLAS/OpenMP thread by its
    environment; the caller's environment is left as it was."""
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    out = list(ProcessExecutor(2).map(thread_env, range(8), chunksize=1))
    assert len({pid for pid, _ in out}) == 2 and {env for _, env in out} == {"1"}
    assert os.environ["OMP_NUM_THREADS"] == "7"


def test_a_lambda_is_refused_by_processes_with_a_clear_error():
    with pytest.raises(ConfigError, match="module-level function"):
        list(ProcessExecutor(2).map(lambda x: x, [1, 2]))


def test_make_get_and_use_executor():
    assert make_executor("local", 1) is SERIAL and get_executor() is SERIAL and get_executor(1) is SERIAL
    ex = make_executor("local", 3)
    assert isinstance(ex, ProcessExecutor) and ex.workers == 3
    assert isinstance(get_executor(4), ProcessExecutor) and get_executor(4).workers == 4  # a stage's workers setting
    mine = SerialExecutor(single_thread_blas=False)
    with use_executor(mine):
        assert get_executor(4) is mine  # the run's executor wins over a stage's workers setting
        with use_executor("local", workers=2) as inner:
            assert get_executor() is inner and inner.workers == 2
        assert get_executor() is mine
    assert get_executor() is SERIAL
    with pytest.raises(ConfigError, match="kind"):
        make_executor("dask")
    with pytest.raises(ConfigError, match="Ray"):
        make_executor("local", 2, address="10.0.0.1:6379")


def test_ray_missing_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(MapkitError, match=r'pip install -e "\.\[distributed\]"'):
        make_executor("ray", 2)


# --------------------------------------------------------------------------- real mapkit work: serial == process pool


def test_semidense_keyframes_serial_equals_process_pool(room):  # noqa: F811 (the module fixture imported from test_semidense, requested by name)
    poses, images = room
    frames = [
        (i, 1_000_000_000 + i * 100_000_000, img, T) for i, (img, T) in enumerate(zip(images, poses, strict=True))
    ]
    maps = {
        kind: build_semidense_map(iter(frames), K_SYN, ROOM_CFG, progress=False, executor=EXECUTORS[kind]())
        for kind in EXECUTORS
    }
    a, b = maps["serial"], maps["process"]
    assert len(a) > 1000
    for field in (
        "points_world",
        "sigma_depth",
        "intensity",
        "source_keyframe",
        "obs_indptr",
        "obs_frame_ids",
        "keyframe_ids",
        "keyframe_world_from_cam",
    ):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)


def test_icp_of_submap_pairs_serial_equals_process_pool():
    world = street(np.random.default_rng(3))
    rng = np.random.default_rng(5)
    clouds = []
    for k, shift in enumerate([(0.0, 0.0, 0.0), (0.6, -0.4, 0.1), (-0.5, 0.3, 0.0)]):
        pts = world[rng.random(len(world)) < 0.15]
        pts = pts + rng.normal(0, 0.03, pts.shape) + np.asarray(shift)
        clouds.append(SubmapClouds(f"s{k}", pts, np.zeros(len(pts), np.int64), np.array([[60.0, -2.0, 0.0]])))
    pairs = [(0, 0, 1, 0, "semidense"), (1, 0, 2, 0, "semidense")]  # each pair names the maps it is registered on
    shared = ({"semidense": clouds, "lidar": [None, None, None]}, AlignConfig())
    got = {kind: list(EXECUTORS[kind]().map(_register_task, pairs, shared=shared)) for kind in EXECUTORS}
    for a, b in zip(got["serial"], got["process"], strict=True):
        np.testing.assert_array_equal(a.target_from_source, b.target_from_source)
        assert (a.fitness, a.rmse_m, a.structure_rmse_m, a.accepted) == (
            b.fitness,
            b.rmse_m,
            b.structure_rmse_m,
            b.accepted,
        )
    # and the registrations are right: s1 is s0 moved by (0.6, -0.4, 0.1)
    np.testing.assert_allclose(got["serial"][0].target_from_source[:3, 3], [0.6, -0.4, 0.1], atol=0.1)
    assert got["serial"][0].accepted


# --------------------------------------------------------------------------- Ray


@pytest.fixture(scope="module")
def ray_executor():
    pytest.importorskip("ray", reason='Ray is not installed (pip install -e ".[distributed]")')
    import ray

    if ray.is_initialized():
        pytest.skip("a Ray instance is already running in this process")
    ex = make_executor("ray", workers=2)
    yield ex
    ex.close()


def test_ray_keeps_the_contract(ray_executor):
    ex = ray_executor
    assert ex.kind == "ray" and ex.workers == 2 and not ex.in_process
    assert list(ex.map(slow_square, range(12))) == [x * x for x in range(12)]
    got = []
    with pytest.raises(TaskError) as e:
        for r in ex.map(inverse, [1.0, 2.0, 0.0, 4.0], desc="inverse"):
            got.append(r)
    assert got == [1.0, 0.5] and e.value.index == 2 and isinstance(e.value.cause, ZeroDivisionError)
    values = np.arange(40, dtype=np.float64)
    out = list(ex.map(lookup, range(40), shared=CountedShared(values), chunksize=2))
    assert [v for v, _, _ in out] == list(values)
    assert set(n for _, _, n in out) == {1}  # 20 tasks, one arrival of the shared state per worker process


# A local Ray instance must not join whatever cluster the machine advertises, and must not listen beyond
# loopback. Each case runs its driver in a subprocess (a fresh Ray per process) with its own Ray temp folder
# (RAY_TMPDIR: where Ray keeps ray_current_cluster and the sessions) and its own auth token (RAY_AUTH_TOKEN:
# ~/.ray is not touched); every process it leaves is found by that RAY_TMPDIR in its environment.

RAY_DRIVER = r"""
import json, os, socket, sys
from mapkit.core.executor import make_executor

def listening():  # inode -> (address, port) of the sockets in LISTEN state
    out = {}
    for name, fam in (("/proc/net/tcp", socket.AF_INET), ("/proc/net/tcp6", socket.AF_INET6)):
        for line in open(name).read().splitlines()[1:]:
            f = line.split()
            if f[3] != "0A":
                continue
            ip, port = f[1].split(":")
            raw = bytes.fromhex(ip)
            raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))  # little-endian words
            out[f[9]] = (socket.inet_ntop(fam, raw), int(port, 16))
    return out

def descendants(root):
    children = {}
    for d in filter(str.isdigit, os.listdir("/proc")):
        try:
            ppid = int(open(f"/proc/{d}/stat").read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(d))
    found, todo = [], [root]
    while todo:
        pid = todo.pop()
        found.append(pid)
        todo += children.get(pid, [])
    return found

def sockets_of(pids):
    table, out = listening(), []
    for pid in pids:
        try:
            name = open(f"/proc/{pid}/comm").read().strip()
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if link.startswith("socket:[") and link[8:-1] in table:
                out.append([name, *table[link[8:-1]]])
    return out

ex = make_executor("ray", workers=2, address=sys.argv[1] or None)
values = list(ex.map(abs, [-3, -2, -1, 0, 1, 2, 3]))
import ray
report = {"workers": ex.workers, "results": values, "nodes": [n["NodeManagerAddress"] for n in ray.nodes()],
          "gcs": ray.get_runtime_context().gcs_address, "sockets": sockets_of(descendants(os.getpid()))}
ex.close()
print("REPORT " + json.dumps(report))
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _processes_of(ray_tmp: Path) -> list[int]:
    """Processes whose environment names this Ray temp folder: the driver, GCS, raylet, agents, workers."""
    mark = f"RAY_TMPDIR={ray_tmp}".encode()
    pids = []
    for d in filter(str.isdigit, os.listdir("/proc")):
        try:
            if mark in Path(f"/proc/{d}/environ").read_bytes().split(b"\0"):
                pids.append(int(d))
        except OSError:
            continue
    return pids


@pytest.fixture
def ray_env():
    """A private Ray temp folder and token, and a check that no Ray process of it outlives the test."""
    pytest.importorskip("ray", reason='Ray is not installed (pip install -e ".[distributed]")')
    ray_tmp = Path(tempfile.mkdtemp(prefix="mkray"))  # short: Ray's unix sockets live below it (108-byte limit)
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env.update(
        RAY_TMPDIR=str(ray_tmp),
        RAY_AUTH_MODE="token",
        RAY_AUTH_TOKEN=secrets.token_hex(32),
        RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S="0",
        RAY_USAGE_STATS_ENABLED="0",
    )
    yield ray_tmp, env
    deadline = time.monotonic() + 15
    while (left := _processes_of(ray_tmp)) and time.monotonic() < deadline:
        time.sleep(0.5)
    for pid in left:
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
    shutil.rmtree(ray_tmp, ignore_errors=True)
    assert not left, f"Ray processes left behind: {left}"


def _run_driver(env: dict, address: str = "") -> dict:
    r = subprocess.run(
        [sys.executable, "-c", RAY_DRIVER, address], env=env, capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr[-3000:]
    line = next(x for x in r.stdout.splitlines() if x.startswith("REPORT "))
    return dict(json.loads(line[len("REPORT ") :]), stderr=r.stderr)


def _loopback(host: str) -> bool:
    return host in ("127.0.0.1", "::1", "::ffff:127.0.0.1") or host.startswith("127.")


def test_local_ray_ignores_a_stale_cluster_and_ray_address_and_listens_on_loopback_only(ray_env):
    ray_tmp, env = ray_env
    dead = f"127.0.0.1:{_free_port()}"  # nothing listens there
    (ray_tmp / "ray").mkdir()
    (ray_tmp / "ray" / "ray_current_cluster").write_text(dead)  # what a crashed `ray start` leaves in /tmp/ray
    env["RAY_ADDRESS"] = dead
    got = _run_driver(env)
    assert got["workers"] == 2 and got["results"] == [3, 2, 1, 0, 1, 2, 3]
    assert "RAY_ADDRESS" in got["stderr"] and "ignored" in got["stderr"]
    assert got["nodes"] == ["127.0.0.1"] and got["gcs"].startswith("127.0.0.1:") and got["gcs"] != dead
    names = {name for name, _, _ in got["sockets"]}
    assert {"gcs_server", "raylet"} <= names, got["sockets"]  # the Ray processes were found
    wide = [s for s in got["sockets"] if not _loopback(s[1])]
    assert not wide, f"Ray listens beyond loopback: {wide}"
    assert (ray_tmp / "ray" / "ray_current_cluster").read_text() == dead  # left as it was


def test_an_explicit_address_joins_a_running_cluster(ray_env, tmp_path):
    ray_tmp, env = ray_env
    env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = (
        "0"  # keep 127.0.0.1 as the node IP (Ray otherwise swaps in a routable one)
    )
    port = _free_port()
    with open(tmp_path / "head.log", "w") as log:
        head = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "ray.scripts.scripts",
                "start",
                "--head",
                "--block",
                "--node-ip-address",
                "127.0.0.1",
                "--port",
                str(port),
                "--include-dashboard=false",
                "--num-cpus",
                "1",
                "--disable-usage-stats",
            ],
            env=env,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    try:
        deadline = time.monotonic() + 60
        while True:
            assert head.poll() is None, (tmp_path / "head.log").read_text()[-3000:]
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
            assert time.monotonic() < deadline, "the Ray head did not start within 60 s"
            time.sleep(0.3)
        got = _run_driver(env, f"127.0.0.1:{port}")
        assert got["workers"] == 1  # the cluster's one CPU, not the 2 asked for: it joined
        assert got["results"] == [3, 2, 1, 0, 1, 2, 3] and got["gcs"] == f"127.0.0.1:{port}"
    finally:  # `ray stop` would stop every Ray on the machine: stop this head (it stops what it started)
        head.terminate()
        try:
            head.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)
            head.wait()


# the tiny preset's two training drives (configs/synth/tiny.yaml) cut to 24 m: enough images for these
# executor checks, in a few seconds (the preset's own 250 m drives are for the demo's every stage)
TINY_TRAIN = {
    "sessions": [
        {
            "name": "tiny-sunny",
            "role": "train",
            "date": "2014-06-26",
            "time": "09:24",
            "weather": "sunny",
            "length_m": 24.0,
            "speed_mps": 9.0,
            "lane_offset_m": 0.0,
        },
        {
            "name": "tiny-rainy",
            "role": "train",
            "date": "2014-10-30",
            "time": "11:11",
            "weather": "rainy",
            "length_m": 24.0,
            "speed_mps": 8.0,
            "lane_offset_m": 0.4,
        },
    ]
}


@pytest.fixture(scope="module")
def tiny_workspace(tmp_path_factory) -> Path:
    """The synthetic ``tiny`` town's training drives, built (mapkit build: maps and image databases)."""
    from mapkit.mapping.build import build
    from mapkit.synth import synthesize

    root = tmp_path_factory.mktemp("tiny")
    town = synthesize(preset="tiny", out=root / "town", overrides=TINY_TRAIN, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)  # tiny's drives are too short to georeference
        return build(session_logs(town), root / "ws", config=_no_lidar_map(root), progress=False)


def _no_lidar_map(folder: Path) -> Path:
    """A build config without the LiDAR map: the stages these tests compare are the camera's."""
    (folder / "no-lidar-map.yaml").write_text("lidar_map: false\n")
    return folder / "no-lidar-map.yaml"


def test_tiny_town_vlad_index_is_identical_on_ray(tiny_workspace, ray_executor, tmp_path):
    from test_index_vlad import SMALL_VLAD

    from mapkit.retrieval.index_vlad import VladIndex, build_vlad_index

    ws = tiny_workspace
    # the demo's index build (its training sessions train and are indexed) with test_index_vlad's small encoder
    overrides = {
        "vlad": SMALL_VLAD.model_dump(),
        "train_sessions": ["tiny-rainy", "tiny-sunny"],
        "database_sessions": ["tiny-rainy", "tiny-sunny"],
    }
    serial = build_vlad_index(ws, tmp_path / "serial", overrides=overrides, progress=False, executor=SERIAL)
    on_ray = build_vlad_index(ws, tmp_path / "ray", overrides=overrides, progress=False, executor=ray_executor)
    a, b = VladIndex.load(serial), VladIndex.load(on_ray)
    assert len(a) > 20
    np.testing.assert_array_equal(a.vectors(), b.vectors())
    for f in ("index.faiss", "database.csv", "encoder/vlad_encoder.npz"):
        assert (serial / f).read_bytes() == (on_ray / f).read_bytes(), f


def test_vlad_encoding_reports_an_unreadable_image_as_its_input_error(tmp_path):
    from test_index_vlad import SMALL_VLAD

    from mapkit.retrieval.index_vlad import _map, _raw_task
    from mapkit.retrieval.vlad import VladEncoder

    vocabulary = np.random.default_rng(0).random((SMALL_VLAD.num_words, 128), dtype=np.float32)
    missing = tmp_path / "gone.png"
    with pytest.raises(InputError, match="cannot read this image") as e:
        list(_map(_raw_task, [str(missing)], VladEncoder(SMALL_VLAD, vocabulary), ProcessExecutor(2), False, "encode"))
    assert e.value.path == missing


def _session_files(ws: Path) -> dict[str, bytes]:
    keep = (
        "trajectory/poses_tum.txt",
        "georef/trajectory_enu/poses_tum.txt",
        "map/points.ply",
        "map/observations.npz",
        "imagedb/images.csv",
    )
    return {
        str(p.relative_to(ws)): p.read_bytes()
        for p in sorted((ws / "sessions").rglob("*"))
        if str(p.relative_to(ws / "sessions")).split("/", 1)[-1] in keep
    }


def test_sessions_built_in_parallel_equal_a_serial_build(tiny_workspace, tmp_path):
    import open3d as o3d

    from mapkit.mapping.build import build

    logs = session_logs(tiny_workspace.parent / "town")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputWarning)
        parallel = build(logs, tmp_path / "ws", _no_lidar_map(tmp_path), progress=False, executor=ProcessExecutor(2))
    a, b = _session_files(tiny_workspace), _session_files(parallel)
    assert len(a) == 5 * len(logs) and a.keys() == b.keys()
    # bit for bit, except the map's float coordinates: a worker runs BLAS on one thread, which sums
    # in another order than this process's BLAS (differences of ~1e-13 m); integers all equal
    assert [k for k in a if a[k] != b[k] and "/map/" not in k] == []
    for k in (k for k in a if "/map/" in k):
        if k.endswith(".ply"):
            pa, pb = (np.asarray(o3d.io.read_point_cloud(str(w / k)).points) for w in (tiny_workspace, parallel))
            assert len(pa) > 500 and pa.shape == pb.shape
            np.testing.assert_allclose(pa, pb, rtol=0, atol=1e-9)
        else:
            na, nb = np.load(tiny_workspace / k), np.load(parallel / k)
            assert na.files == nb.files
            for f in na.files:
                if na[f].dtype.kind == "f":
                    np.testing.assert_allclose(na[f], nb[f], rtol=0, atol=1e-9, err_msg=f)
                else:
                    np.testing.assert_array_equal(na[f], nb[f], err_msg=f)


def test_parallel_build_fixes_the_workspace_frame_first(tiny_workspace, tmp_path):
    """Given-origin georeferencing (a pose stream in ENU): every session in one frame, the one a serial build sets."""
    from mapkit.mapping.build import build

    logs = session_logs(tiny_workspace.parent / "town")
    cfg = Path(__file__).resolve().parents[1] / "configs" / "build" / "mcvl-database.yaml"
    serial = build(logs, tmp_path / "serial", cfg, progress=False, executor=SERIAL)
    parallel = build(logs, tmp_path / "parallel", cfg, progress=False, executor=ProcessExecutor(2))
    assert (serial / "origin.json").read_bytes() == (parallel / "origin.json").read_bytes()
    for log in logs:
        csv = Path("sessions") / log.stem / "imagedb" / "images.csv"
        assert (serial / csv).read_bytes() == (parallel / csv).read_bytes()
