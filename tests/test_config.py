import pytest

from uwb_env.config import CalibrationConfig, ConfigError, MotionConfig, SimConfig


def test_defaults_construct():
    cfg = SimConfig()
    assert cfg.n_anchors == 4 and cfg.dim == 2
    assert SimConfig.from_dict(cfg.to_dict()) == cfg


def test_unknown_key_names_the_field():
    with pytest.raises(ConfigError) as err:
        SimConfig.from_dict({"n_anchor": 4})
    assert err.value.field == "n_anchor"
    with pytest.raises(ConfigError) as err:
        SimConfig.from_dict({"ranging": {"nlos_prob": 0.1}})
    assert err.value.field == "ranging.nlos_prob"


@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"dt_s": 0.0}, "dt_s"),
        ({"dt_s": float("nan")}, "dt_s"),
        ({"n_anchors": 2}, "n_anchors"),
        ({"dim": 3, "n_anchors": 3}, "n_anchors"),
        ({"dim": 4}, "dim"),
        ({"n_anchors": 4.0}, "n_anchors"),
        ({"ranging": {"nlos_probability": 1.5}}, "ranging.nlos_probability"),
        ({"ranging": {"max_range_m": -1}}, "ranging.max_range_m"),
        ({"odometry": {"model": "magic"}}, "odometry.model"),
        ({"anchor_motion": {"speed_min_mps": 2.0, "speed_max_mps": 1.0}}, "anchor_motion.speed_max_mps"),
        ({"calibration": {"measurements_per_pair": 0}}, "calibration.measurements_per_pair"),
        ({"calibration": {"reference_latencies_s": [[5, 0.9]]}}, "calibration.reference_latencies_s"),
    ],
)
def test_invalid_values_raise_with_field_and_value(overrides, field):
    with pytest.raises(ConfigError) as err:
        SimConfig.from_dict(overrides)
    assert err.value.field == field
    assert field.split(".")[-1] in str(err.value)


def test_replace_merges_nested_and_keeps_the_rest():
    cfg = SimConfig().replace(ranging={"nlos_probability": 0.2}, dt_s=0.5)
    assert cfg.ranging.nlos_probability == 0.2
    assert cfg.ranging.dropout_probability == SimConfig().ranging.dropout_probability
    assert cfg.dt_s == 0.5


def test_configs_are_frozen():
    with pytest.raises(AttributeError):
        MotionConfig().speed_min_mps = 3.0  # type: ignore[misc]


def test_yaml_style_lists_become_tuples():
    cfg = CalibrationConfig.from_dict({"reference_latencies_s": [[5, 1.0], [50, 3.0]]})
    assert cfg.reference_latencies_s == ((5, 1.0), (50, 3.0))
