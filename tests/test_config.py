"""Cell configs load, and every error names the file, the key and the problem."""

from __future__ import annotations

from pathlib import Path

import pytest
from scancell.cli._common import default_cell_config
from scancell.config import ConfigError, load_cell_config
from scancell.deploy import cell_config_path


@pytest.mark.unit
def test_packaged_configs_load():
    cfg = load_cell_config(default_cell_config())
    assert cfg.cell and cfg.devices
    mock = load_cell_config(cell_config_path("mock"))
    assert {d.driver for d in mock.devices.values()} >= {"mock_robot", "mock_tracker"}
    assert mock.bus.listen == ("tcp/127.0.0.1:7447",) and not mock.bus.multicast_scouting



@pytest.mark.unit
@pytest.mark.parametrize("name", ["sim", "sim-car-body"])
def test_the_simulated_cells_robot_driver_knows_the_simulated_arms_limits(name):
    """The driver checks a plan's every pose at its start against its limits; with the
    controller's wider than its own a plan could pass and be refused mid-run."""
    import numpy as np
    from scancell.model.robot_model import M710IC_LIMITS_DEG

    robot = load_cell_config(cell_config_path(name)).devices["robot"]
    np.testing.assert_array_equal(robot.options["joint_limits_deg"], M710IC_LIMITS_DEG)

def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cell.toml"
    p.write_text(text)
    return p


@pytest.mark.unit
@pytest.mark.parametrize("text,expected", [
    ("[cell\nname='x'", "not valid TOML"),
    ("[cell]\nname='x'\n[robots]\n", "robots: unknown table"),
    ("[cell]\nname='a/b'\n", "[cell] name: invalid cell name"),
    ("[cell]\nname='x'\n[devices.robot]\nurl='x'\n", "[devices.robot] driver: missing"),
    ("[cell]\nname='x'\n[devices.robot]\ndriver='fanuc9'\n",
     "[devices.robot] driver: unknown driver 'fanuc9'; known:"),
    ("[cell]\nname='x'\n[daemon]\nstatus_period_s=-1\n", "[daemon] status_period_s: must be"),
    ("[cell]\nname='x'\n[daemon]\nfoo=1\n", "[daemon] foo: unknown key"),
    ("[cell]\nname='x'\n[bus]\nlisten='tcp/1.2.3.4:1'\n", "[bus]: listen must be a list"),
    ("[cell]\nname='x'\n[bus]\nuser='u'\n", "[bus]: give both user and password"),
    ("[cell]\nname='x'\n[devices.'a b']\ndriver='mock_robot'\n", "invalid device name"),
    ("[cell]\nname='x'\n[inspection]\nnominl='a.step'\n", "[inspection]: unknown key 'nominl'"),
    ("[cell]\nname='x'\n[inspection]\nalign='rps'\n", "[inspection] align: must be"),
    ("[cell]\nname='x'\n[inspection]\ndecision_rule='lenient'\n",
     "[inspection] decision_rule: must be iso14253-1 or simple, got 'lenient'"),
    ("[cell]\nname='x'\n[inspection]\npoint_sigma_mm=-0.1\n",
     "[inspection] point_sigma_mm: must be a number >= 0"),
    ("[cell]\nname='x'\n[inspection]\nT_world_from_part=[1,2]\n",
     "[inspection] T_world_from_part: must be a 4x4"),
    ("[cell]\nname='x'\n[acceptance]\nsphere_diameter_mm=50\n", "[acceptance]: missing"),
    ("[cell]\nname='x'\n[acceptance]\nvolume_size_mm=[1,2]\nvolume_centre_mm=[0,0,600]\n"
     "sphere_diameter_mm=50\nballbar_length_mm=200\nballbar_sphere_diameter_mm=30\n"
     "plane_size_mm=[200,50]\n", "[acceptance] volume_size_mm: must be 3 positive lengths"),
    ("[cell]\nname='x'\n[acceptance]\nvolume_size_mm=[1,2,3]\nvolume_centre_mm=[0,0,600]\n"
     "sphere_diameter_mm=50\nballbar_length_mm=200\nballbar_sphere_diameter_mm=30\n"
     "plane_size_mm=[200,50]\nmpe_mm={PX=1}\n", "[acceptance] mpe_mm: must map F, PF, PS, SD"),
    ("[cell]\nname='x'\n[acceptance]\nvolume_size_mm=[1,2,3]\nvolume_centre_mm=[0,0,600]\n"
     "sphere_diameter_mm=50\nballbar_length_mm=200\nballbar_sphere_diameter_mm=30\n"
     "plane_size_mm=[200,50]\ntest_u_mm={PF=-1}\n",
     "[acceptance] test_u_mm: must map F, PF, PS, SD, SD3 to positive numbers"),
    ("[cell]\nname='x'\n[acceptance]\nvolume_size_mm=[1,2,3]\nvolume_centre_mm=[0,0,600]\n"
     "sphere_diameter_mm=50\nballbar_length_mm=200\nballbar_sphere_diameter_mm=30\n"
     "plane_size_mm=[200,50]\ndecision_rule='lenient'\n",
     "[acceptance] decision_rule: must be iso14253-1 or simple, got 'lenient'"),
    ("[cell]\nname='x'\n[acceptance]\nvolume_size_mm=[1,2,3]\nvolume_centre_mm=[0,0,600]\n"
     "sphere_diameter_mm=50\nballbar_length_mm=200\nballbar_sphere_diameter_mm=30\n"
     "plane_size_mm=[200,50]\nmpe_camera_width_px=0\n",
     "[acceptance] mpe_camera_width_px: must be a positive whole number of pixels, got 0"),
    ("[cell]\nname='x'\n[acceptance]\nvolume_size_mm=[1,2,3]\nvolume_centre_mm=[0,0,600]\n"
     "sphere_diameter_mm=50\nballbar_length_mm=200\nballbar_sphere_diameter_mm=30\n"
     "plane_size_mm=[200,50]\nballbar3_length_mm=800\n", "a Part 3 test needs all of"),
    ("[cell]\nname='x'\n[scanner]\ndecode_limits={bend_px=1}\n",
     "[scanner] decode_limits: decode_limits: unknown limit(s) ['bend_px']"),
    ("[cell]\nname='x'\n[scanner]\ndecode_limits={bend_limit_px='wide'}\n",
     "decode_limits.bend_limit_px = 'wide': must be a number"),
    ("[cell]\nname='x'\n[scanner]\ndecode_limits={z_min_mm=900, z_max_mm=100}\n",
     "z_min_mm 900.0 must be below z_max_mm 100.0"),
    ("[cell]\nname='x'\n[scanner]\ndecode_limits=3\n", "must be a table of limits"),
    ("[cell]\nname='x'\n[scanner]\nwarmup_min=-5\n",
     "[scanner] warmup_min: must be a number of minutes from 0 to 1440, got -5"),
    ("[cell]\nname='x'\n[scanner]\nwarmup_min='1h'\n", "got '1h'"),
])
def test_errors_name_file_key_and_problem(tmp_path, text, expected):
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as ei:
        load_cell_config(path)
    assert str(path) in str(ei.value)
    assert expected in str(ei.value)


@pytest.mark.unit
def test_inspection_table_paths_are_relative_to_the_config(tmp_path):
    path = _write(tmp_path, "[cell]\nname='x'\n[inspection]\nnominal='cad/part.step'\n"
                            "tolerance_mm=0.5\nalign='asmeasured'\n"
                            "T_world_from_part=[[1,0,0,3300],[0,1,0,0],[0,0,1,-100],[0,0,0,1]]\n")
    t = load_cell_config(path).inspection
    assert t["nominal"] == str(tmp_path / "cad" / "part.step") and t["tolerance_mm"] == 0.5


@pytest.mark.unit
def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read cell config"):
        load_cell_config(tmp_path / "nope.toml")


@pytest.mark.unit
def test_driver_options_checked_against_driver_schema(tmp_path, monkeypatch):
    from scancell.devices import mock

    monkeypatch.setattr(mock.MockAxis, "OPTIONS_SCHEMA", {
        "type": "object", "properties": {"limits": {"type": "array", "items": {"type": "number"}}}})
    path = _write(tmp_path, "[cell]\nname='x'\n[devices.axis]\ndriver='mock_axis'\nlimits=['a']\n")
    with pytest.raises(ConfigError, match=r"\[devices.axis\] limits.0: 'a' is not of type"):
        load_cell_config(path)


@pytest.mark.unit
def test_bus_tls_and_auth_reach_zenoh_config():
    from scancell.bus import BusConfig

    cfg = BusConfig.from_mapping({"mode": "client", "connect": ["tls/router:7447"],
                                  "tls": {"root_ca_certificate": "/etc/ca.pem"},
                                  "user": "ctl", "password": "pw"})
    z = cfg.to_zenoh()
    assert '"/etc/ca.pem"' in z.get_json("transport/link/tls/root_ca_certificate")
    assert '"ctl"' in z.get_json("transport/auth/usrpwd/user")
    with pytest.raises(ValueError, match="tls: unknown key"):
        BusConfig.from_mapping({"tls": {"cert": "x"}})
