"""Typed node configurations (`ros_nodes.params`) directly: flat names, round trip, bounds,
cross-field checks and ROS 2 YAML parameter files."""

import dataclasses

import pytest

from ros_nodes import params as P
from ros_nodes import topics
from ros_nodes.registry import NODES, RIG

CONFIGS = [P.ShakerNodeConfig, P.StageNodeConfig, P.CameraNodeConfig, P.RecorderNodeConfig]


@pytest.mark.parametrize("cls", CONFIGS)
def test_every_parameter_is_documented_and_round_trips(cls):
    specs = P.flat_fields(cls)
    assert specs and len({s.name for s in specs}) == len(specs)
    for s in specs:
        assert s.description, s.name
        assert P.check_value(s, s.default) == s.default
        if s.min is not None and s.max is not None:
            assert s.min <= s.default <= s.max, s.name
    flat = P.to_flat(cls())
    assert list(flat) == [s.name for s in specs]
    assert P.from_flat(cls, flat) == cls()


def test_nested_device_configs_are_dotted_and_rebuilt():
    names = [s.name for s in P.flat_fields(P.ShakerNodeConfig)]
    assert "device.max_amplitude_m" in names and "rate_hz" in names
    cfg = P.from_flat(P.ShakerNodeConfig, {"device.max_amplitude_m": 0.008, "rate_hz": 500})
    assert cfg.device.max_amplitude_m == 0.008 and cfg.rate_hz == 500.0
    assert isinstance(cfg.rate_hz, float)  # an int given for a float parameter is coerced
    again = P.from_flat(P.ShakerNodeConfig, P.to_flat(cfg))
    assert again == cfg
    # `base`: values over an existing config, not over the defaults
    assert P.from_flat(P.ShakerNodeConfig, {"seed": 3}, base=cfg).device.max_amplitude_m == 0.008


@pytest.mark.parametrize("values, match", [
    ({"rate_hz": 0.5}, "below the minimum"),
    ({"rate_hz": 1e9}, "above the maximum"),
    ({"rate_hz": float("nan")}, "NaN"),
    ({"rate_hz": "fast"}, "expected float"),
    ({"seed": True}, "expected int"),
    ({"hardware": "real"}, "choose one of sim"),
    ({"device.max_amplitude_m": 0.5}, "above the maximum"),
    ({"no_such": 1}, "unknown parameter"),
    # a cross-field check of the nested device config, reported with its prefix
    ({"device.min_frequency_hz": 300.0}, "device"),
])
def test_bad_values_are_refused_with_the_reason(values, match):
    with pytest.raises(P.ConfigError, match=match):
        P.from_flat(P.ShakerNodeConfig, values)


def test_topic_lists_are_strings():
    cfg = P.from_flat(P.RecorderNodeConfig, {"topics": ["/a", "/b"]})
    assert cfg.topics == ("/a", "/b")
    with pytest.raises(P.ConfigError, match="list of strings"):
        P.from_flat(P.RecorderNodeConfig, {"topics": "/a"})


def test_the_recorder_records_the_rig_topics_by_default():
    recorded = P.RecorderNodeConfig().topics
    assert recorded == topics.RECORDED
    assert set(recorded) <= set(topics.BY_NAME)
    assert "/shaker/fire_request" not in recorded  # nothing publishes it
    assert P.CameraNodeConfig().image_topic == topics.IMAGE.name


def test_yaml_files_use_the_ros2_layout(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    seed: 7\n"
                 "shaker:\n  ros__parameters:\n    device:\n      max_amplitude_m: 0.008\n"
                 "    rate_hz: 800.0\n"
                 "recorder:\n  ros__parameters:\n    topics: [/clock, /rig/stop]\n")
    shaker = P.load_yaml(f, "shaker")
    assert shaker == {"seed": 7, "device.max_amplitude_m": 0.008, "rate_hz": 800.0}
    assert P.from_flat(P.ShakerNodeConfig, shaker).device.max_amplitude_m == 0.008
    assert P.load_yaml(f, "recorder") == {"seed": 7, "topics": ("/clock", "/rig/stop")}
    assert P.load_yaml(f, "stage") == {"seed": 7}


def test_unreadable_yaml_is_a_config_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    for text, problem in (("shaker: [unclosed\n", "not valid YAML (expected ',' or ']'"),
                          ("- 1\n- 2\n", "not a map of node names")):
        bad.write_text(text)
        with pytest.raises(P.ConfigError, match="cannot read parameter file") as e:
            P.load_yaml(bad, "shaker")
        assert problem in str(e.value) and "\n" not in str(e.value)  # one line
    with pytest.raises(P.ConfigError, match="cannot read parameter file"):
        P.load_yaml(tmp_path / "missing.yaml", "shaker")


def test_the_registry_names_each_rig_node_config():
    assert [NODES[n].config() for n in RIG] == CONFIGS
    for cls in CONFIGS:
        assert dataclasses.is_dataclass(cls)


def test_every_configuration_dataclass_declares_its_fields_with_param():
    """One metadata schema for every configuration (`metarig.fields.param`): each dataclass
    named `...Config` in the project's packages gives every field a description and bounds.
    Read from the source (no imports); the solver settings are an equinox module, not a
    dataclass, and are not covered."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    found, bare = 0, []
    for pkg in ("metarig", "design_engine", "tracking", "hardware_sim", "comparison",
                "ros_nodes", "devices"):
        for path in sorted((root / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                is_dataclass = isinstance(node, ast.ClassDef) and any(
                    "dataclass" in ast.unparse(d) for d in node.decorator_list)
                if not (is_dataclass and node.name.endswith("Config")):
                    continue
                found += 1
                for item in node.body:
                    if isinstance(item, ast.AnnAssign) and not (
                            isinstance(item.value, ast.Call)
                            and ast.unparse(item.value.func).endswith("param")):
                        bare.append(f"{path.relative_to(root)}: {node.name}.{ast.unparse(item.target)}")
    assert found >= 10
    assert bare == []
