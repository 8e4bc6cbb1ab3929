"""Configuration loading errors name file and field; run-folder writes are atomic and resumable."""

import json

import pytest

from mapkit.core.config import TopicConfig, defaults_yaml, dump_config, load_config, resolve_topics
from mapkit.core.errors import ConfigError, InputError
from mapkit.core.runio import atomic_write_text, config_hash, is_done, mark_done, write_json
from mapkit.core.types import GpsFix, StreamKind
from mapkit.io.mcap_log import McapLog, McapWriter


def test_yaml_overrides_defaults_and_round_trips(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("gps: /gnss/fix\nimages: [/cam/a, /cam/b]\n")
    cfg = load_config(TopicConfig, p)
    assert cfg.gps == "/gnss/fix" and cfg.images == ["/cam/a", "/cam/b"] and cfg.lidar is None
    p2 = tmp_path / "resolved.yaml"
    p2.write_text(dump_config(cfg))
    assert load_config(TopicConfig, p2) == cfg


@pytest.mark.parametrize(
    "text, match",
    [
        ("gsp: /gps\n", r"c\.yaml: field gsp: Extra inputs are not permitted"),
        ("images: 3\n", r"c\.yaml: field images"),
        ("- a\n- b\n", r"expected a mapping"),
        ("gps: [unclosed\n", r"not valid YAML"),
    ],
)
def test_bad_config_names_file_and_field(tmp_path, text, match):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_config(TopicConfig, p)


def test_missing_config_file(tmp_path):
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(TopicConfig, tmp_path / "nope.yaml")


def test_defaults_yaml_is_commented_and_loadable(tmp_path):
    text = defaults_yaml(TopicConfig)
    assert "# NavSatFix topic" in text
    p = tmp_path / "d.yaml"
    p.write_text(text)
    assert load_config(TopicConfig, p) == TopicConfig()


def _two_gps_log(tmp_path):
    with McapWriter(tmp_path / "g.mcap") as w:
        w.write("/gps/a", GpsFix(1, 49.0, 8.4, 100.0))
        w.write("/gps/b", GpsFix(1, 49.0, 8.4, 100.0))
    return McapLog(tmp_path / "g.mcap")


def test_resolve_topics_demands_a_choice_between_two_gps_streams(tmp_path):
    with _two_gps_log(tmp_path) as log:
        with pytest.raises(InputError, match=r"2 gps streams .*choose one with topics.gps"):
            resolve_topics(log, TopicConfig())
        chosen = resolve_topics(log, TopicConfig(gps="/gps/b"))
        assert chosen[StreamKind.GPS] == ["/gps/b"]
        with pytest.raises(InputError, match=r"'/gps/c' \(config topics.gps\) is not in this log"):
            resolve_topics(log, TopicConfig(gps="/gps/c"))
        with pytest.raises(InputError, match=r"carries gps, not lidar"):
            resolve_topics(log, TopicConfig(gps="/gps/a", lidar="/gps/b"))


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "out.json"
    write_json(target, {"v": 1})

    class Boom:
        pass

    with pytest.raises(TypeError):
        write_json(target, {"v": Boom()})
    assert json.loads(target.read_text()) == {"v": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["out.json"]  # no partial file left behind


def test_done_marker_tracks_config(tmp_path):
    stage = tmp_path / "stage"
    stage.mkdir()
    h = config_hash(TopicConfig(gps="/a"))
    assert h == config_hash(TopicConfig(gps="/a")) and h != config_hash(TopicConfig(gps="/b"))
    assert not is_done(stage)
    atomic_write_text(stage / "result.txt", "x")
    assert not is_done(stage, h)  # output without marker: an interrupted run
    mark_done(stage, h, items=3)
    assert is_done(stage, h) and not is_done(stage, config_hash(TopicConfig(gps="/b")))
