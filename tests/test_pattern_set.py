"""Pattern sets as data (model/pattern_set.py, analysis/pattern_files.py): presets, specs in TOML
and JSON, the projector images they render, and the errors bad specs get."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scancell.analysis.pattern_files import find_frames, load_pattern_set
from scancell.analysis.scanner import ImageSetError
from scancell.model.pattern_set import PRESETS, PatternSet, PatternSpecError, preset
from scancell.model.patterns import FringeSequence

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_round_trips_through_its_spec(name):
    spec = preset(name)
    again = PatternSet.from_dict(json.loads(json.dumps(spec.to_dict())))
    assert again == spec
    assert len(spec) == sum(g.frame_count for g in spec.groups)


def test_the_default_preset_is_the_scanners_fringe_sequence():
    spec = preset("heterodyne-3x3")
    assert spec.fringe_sequence() == FringeSequence()
    assert spec.method("x") == "heterodyne"
    for k in range(9):  # the projector shows the same images as before
        assert np.array_equal(spec.image(k, 1280, 800), FringeSequence().image(k, 1280, 800))
    assert preset("slstudio-2x3").fringe_sequence() == FringeSequence((16.0, 1.0), 3)
    assert preset("slstudio-2x3").method("x") == "hierarchical"
    assert preset("gray-phase").fringe_sequence() is None


def test_slstudio_preset_matches_slstudios_codec():
    """I_n(x) = ½(1 + cos(2π·p·x/W − 2π·n/3)), 16 periods then the 1-period cue, 8-bit."""
    spec = preset("slstudio-2x3")
    W = 1824
    x = np.arange(W)
    for k, (p, n) in enumerate([(16, 0), (16, 1), (16, 2), (1, 0), (1, 1), (1, 2)]):
        want = np.round(255 * 0.5 * (1 + np.cos(2 * np.pi * p * x / W - 2 * np.pi * n / 3)))
        assert np.array_equal(spec.image(k, W, 4)[0], want.astype(np.uint8))


def test_gray_code_frames_number_the_stripes_and_neighbours_differ_in_one_bit():
    spec = PatternSet.from_dict({"groups": [
        {"kind": "phase_shift", "axis": "y", "periods": 16, "steps": 4},
        {"kind": "gray_code", "axis": "y", "bits": 5, "inverse": True}]})
    W, H = 64, 160
    imgs = [spec.image(k, W, H) for k in range(len(spec))]
    assert len(imgs) == 4 + 10 and all(np.all(im == im[:, :1]) for im in imgs)  # rows vary
    bits = np.stack([imgs[4 + 2 * b][:, 0] > 127 for b in range(5)], 1)
    inverse = np.stack([imgs[5 + 2 * b][:, 0] > 127 for b in range(5)], 1)
    assert np.array_equal(bits, ~inverse)
    codes = bits @ (1 << np.arange(4, -1, -1))
    stripes = np.arange(H) // 5  # 160 rows / 32 stripes
    gray = stripes ^ (stripes >> 1)
    assert np.array_equal(codes, gray)
    changed = np.flatnonzero(np.diff(codes))
    assert all(bin(int(codes[i]) ^ int(codes[i + 1])).count("1") == 1 for i in changed)


def test_groups_may_sit_anywhere_in_the_sequence_with_their_own_steps():
    spec = PatternSet.from_dict({"groups": [
        {"kind": "phase_shift", "axis": "x", "periods": 1, "steps": 3, "first": 5},
        {"kind": "phase_shift", "axis": "x", "periods": 12, "steps": 5, "first": 0}]})
    assert spec.placement() == [5, 0] and len(spec) == 8
    assert spec.method("x") == "hierarchical"
    assert list(spec.frames_of(spec.groups[0])) == [5, 6, 7]


@pytest.mark.parametrize("groups, message", [
    ([{"kind": "fringes", "axis": "x"}], "kind"),
    ([{"kind": "phase_shift", "axis": "z", "periods": 8, "steps": 3}], "axis"),
    ([{"kind": "phase_shift", "axis": "x", "periods": 8, "steps": 2}], "at least 3 steps"),
    ([{"kind": "phase_shift", "axis": "x", "periods": 8, "period_px": 20, "steps": 3}], "exactly one"),
    ([{"kind": "phase_shift", "axis": "x", "periods": 8, "steps": 3}], "cannot be unwrapped"),
    ([{"kind": "gray_code", "axis": "x", "bits": 5}], "phase_shift group"),
    ([{"kind": "phase_shift", "axis": "x", "periods": 8, "steps": 3, "first": 2},
      {"kind": "phase_shift", "axis": "x", "periods": 1, "steps": 3, "first": 0}], "both claim frame 2"),
    ([{"kind": "phase_shift", "axis": "x", "periods": 8, "steps": 3, "colour": "red"}], "colour"),
])
def test_a_bad_spec_names_the_group_and_field(groups, message):
    with pytest.raises(PatternSpecError, match=message) as err:
        PatternSet.from_dict({"groups": groups}, "my.toml")
    assert "my.toml" in str(err.value)


def test_a_gray_code_that_cannot_cover_the_projector_is_refused():
    spec = PatternSet.from_dict({"groups": [
        {"kind": "phase_shift", "axis": "x", "period_px": 32, "steps": 4},
        {"kind": "gray_code", "axis": "x", "bits": 5, "stripe_px": 32}]})
    spec.check_projector(1024, 768)  # 32 stripes of 32 px cover 1024 columns
    with pytest.raises(PatternSpecError, match=r"groups\[1\].*1024 px, short of the projector's "
                                               r"1280 px along x: it needs 6 bits"):
        spec.check_projector(1280, 800)


def test_spec_files_in_toml_and_json_and_their_errors(tmp_path):
    toml = tmp_path / "rig.toml"
    toml.write_text('name = "mine"\nframes = "cam_*.bmp"\n[[groups]]\nkind = "phase_shift"\n'
                    'axis = "x"\nperiods = 16\nsteps = 3\n[[groups]]\nkind = "phase_shift"\n'
                    'axis = "x"\nperiods = 1\nsteps = 3\n[limits]\nmin_modulation_dn = 6\n')
    spec = load_pattern_set(toml)
    assert spec.name == "mine" and spec.limits == {"min_modulation_dn": 6.0}
    js = tmp_path / "rig.json"
    js.write_text(json.dumps(spec.to_dict()))
    assert load_pattern_set(js) == spec
    bad = tmp_path / "bad.toml"
    bad.write_text("groups = [")
    with pytest.raises(PatternSpecError, match=r"bad.toml: not valid TOML"):
        load_pattern_set(bad)
    with pytest.raises(PatternSpecError, match="neither a preset"):
        load_pattern_set(tmp_path / "missing.toml")
    lim = tmp_path / "lim.toml"
    lim.write_text(toml.read_text().replace("min_modulation_dn", "min_modulation"))
    with pytest.raises(PatternSpecError, match=r"lim.toml: limits: unknown key\(s\) \['min_modulation'\]"):
        load_pattern_set(lim)


def test_frames_are_found_by_glob_or_in_natural_name_order(tmp_path):
    spec = preset("slstudio-2x3")
    for k in (0, 1, 2, 3, 4, 10):
        (tmp_path / f"f{k}.png").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("x")
    assert [p.name for p in find_frames(tmp_path, spec)] == [f"f{k}.png" for k in (0, 1, 2, 3, 4, 10)]
    (tmp_path / "f11.png").write_bytes(b"")
    with pytest.raises(ImageSetError, match=r"7 frames .* needs 6"):
        find_frames(tmp_path, spec)
    for k in range(12, 17):
        (tmp_path / f"f{k}.png").write_bytes(b"")
    with pytest.raises(ImageSetError, match=r"12 frames .* presets of 12 frames: slstudio-2x3-xy"):
        find_frames(tmp_path, spec)
    picked = PatternSet.from_dict({**spec.to_dict(), "frames": "f[0-4].png"})
    with pytest.raises(ImageSetError, match=r"5 frames matching 'f\[0-4\].png'"):
        find_frames(tmp_path, picked)


def test_the_decode_help_names_every_preset():
    import argparse

    from scancell.cli import decode

    parser = argparse.ArgumentParser()
    decode.add_arguments(parser)
    text = " ".join(next(a.help for a in parser._actions if a.dest == "patterns").split())
    assert all(name in text for name in PRESETS), text
