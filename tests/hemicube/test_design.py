"""The capture designer (docs/designer.md): design files checked on load, the device costs against the LED
controller's emulator and closed forms, the network with fixed or masked patterns, and `hemicube design
evaluate` end to end on the mini rig."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

import hemicube.cli
import twin
from twin.capture.backends.led_emulator import spawn
from twin.capture.backends.led_host import LedController
from twin.design.costs import acquisition_time, led_duty, upload_cost
from twin.design.design_file import DesignError, load_design
from twin.design.study import load_study, study_lines

DESIGNS = Path(__file__).resolve().parents[2] / "docs" / "designs"
HEAD = 'format = "hemicube-design"\nversion = 1\nrig = "mini"\n'


def _write(tmp_path, body, name="d.toml"):
    p = tmp_path / name
    p.write_text(HEAD + body)
    return p


def test_shipped_designs_load():
    for p in sorted(DESIGNS.glob("*.toml")):
        d = load_design(p)
        assert d.count >= 1 and d.led_on.any() and d.training.seeds
    half = load_design(DESIGNS / "learned-32-half-pitch.toml")
    full = load_design(DESIGNS / "learned-32.toml")
    assert full.led_on.sum() == (~full.rig.is_bottom).sum()
    # every second LED row and column: about a quarter of the LEDs
    assert 0.15 < half.led_on.sum() / full.led_on.sum() < 0.35


def test_rig_override(tmp_path, capsys):
    """--rig puts one rig in place of every design file's (a built-in name or a rig folder): the file's name, layout
    changes and patterns apply on top of it; a rig that cannot be loaded is one line before any work (exit 2). No
    training: the paper rig's networks are for a GPU (docs/designer.md)."""
    from hemicube.design import override_rig
    from twin.rig.format import save_rig

    paper = override_rig("paper")
    d = load_design(DESIGNS / "s11.3-suite-10.toml", paper)  # a mini-rig file scored on the paper rig
    assert (d.name, d.rig.name, d.count) == ("s11.3-suite-10", "paper", 10)
    assert d.led_on.sum() == (~paper.is_bottom).sum() == 12288
    half = load_design(DESIGNS / "learned-32-half-pitch.toml", "paper")  # the file's stride on the paper rig's boards
    assert half.rig is paper and 0.15 < half.led_on.sum() / 12288 < 0.35
    assert load_design(DESIGNS / "s11.3-paper-suite-32.toml", "mini").rig.name == "mini"  # and back
    save_rig(twin.load_rig("mini"), tmp_path / "myrig")
    assert load_design(DESIGNS / "s11.3-paper-suite-32.toml", override_rig(str(tmp_path / "myrig"))).rig.num_leds == \
        twin.load_rig("mini").num_leds
    for cmd in (["evaluate", str(DESIGNS / "learned-10.toml")], ["optimise", str(DESIGNS / "learned-10.toml")]):
        out = tmp_path / f"out-{cmd[0]}"
        assert hemicube.cli.main(["design", *cmd, "--rig", "nonesuch", "-o", str(out), "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert err == "hemicube: error: --rig: 'nonesuch' is neither a built-in rig (paper, mini) nor an existing folder"
        assert not out.exists()


def _bad_pattern_file(tmp_path):
    rig = twin.load_rig("mini")
    levels = np.zeros((4, rig.num_leds, 3), np.int16)
    levels[1, 7, 0] = 300
    np.savez(tmp_path / "bad.npz", levels=levels)
    return 'file = "bad.npz"\n'


@pytest.mark.parametrize("body, field, words", [
    ('colour = 1\n', "colour", "unknown key"),
    ('[leds]\noff = [99999]\n', "leds.off", "not on rig"),
    ('[leds]\noff_boards = ["roof"]\n', "leds.off_boards", "no board 'roof'"),
    ('[leds]\nstride = 0\n', "leds.stride", "integer >= 1"),
    ('[leds]\npitch = 2\n', "leds.pitch", "unknown key"),
    ('[patterns]\nfamily = "sinusoids"\n', "patterns.family", "must be one of"),
    ('[patterns]\nfamily = "olat"\ncount = 100000\n', "patterns.count", "need 100000 LEDs on"),
    ('[patterns]\nfamily = "gradients"\ncount = 8\n', "patterns.count", "has 4 patterns"),
    ('[patterns]\nfamily = "file"\ncount = 2\n', "patterns.file", "needs a pattern file"),
    ('[patterns]\nfamily = "lines"\ncount = 65\n', "patterns.count", "count must be an integer in [1, 64]"),
    ('[leds]\noff_boards = ["top A"]\n[patterns]\nfamily = "lines"\ncount = 64\n', "patterns", "lights no LED"),
    ('[training]\nseeds = [1, 1]\n', "training.seeds", "distinct"),
    ('[training]\ndropout = 1.0\n', "training.dropout", "[0, 1)"),
    ('[capture]\nbaud = -5\n', "capture.baud", "integer >= 1"),
    ('[cameras.secondary]\ncentre_mm = [0.0, 0.0, -400.0]\n', "cameras.secondary", "cannot see"),
    ('[cameras.tertiary]\ncentre_mm = [0.0, 0.0, 400.0]\n', "cameras.tertiary", "no camera"),
])
def test_bad_designs_name_the_field(tmp_path, body, field, words):
    with pytest.raises(DesignError) as e:
        load_design(_write(tmp_path, body))
    msg = str(e.value)
    assert "\n" not in msg and f": {field}: " in msg and words in msg


def test_pattern_file_checks(tmp_path):
    body = '[patterns]\nfamily = "file"\ncount = 2\n' + _bad_pattern_file(tmp_path)
    with pytest.raises(DesignError, match=r"patterns\.file: level 300 at frame 1, LED 7 is outside the "
                                          r"controller's 8 bits"):
        load_design(_write(tmp_path, body))
    from twin.capture.pattern_sets import placeholder_learned
    from twin.capture.patterns import save_patterns

    save_patterns(placeholder_learned(twin.load_rig("mini"), count=3), tmp_path / "three.npz")
    with pytest.raises(DesignError, match=r"patterns\.file: 6 frames, the design's count 2 needs 4"):
        load_design(_write(tmp_path, '[patterns]\nfamily = "file"\ncount = 2\nfile = "three.npz"\n'))
    save_patterns(placeholder_learned(twin.load_rig("paper"), count=2), tmp_path / "paper.npz")
    with pytest.raises(DesignError, match=r"patterns\.file: pattern set has 16384 LEDs per frame"):
        load_design(_write(tmp_path, '[patterns]\nfamily = "file"\ncount = 2\nfile = "paper.npz"\n'))
    d = load_design(_write(tmp_path, '[patterns]\nfamily = "file"\ncount = 3\nfile = "three.npz"\n'))
    w = d.signed_patterns()
    assert w.shape == (3, d.rig.num_leds) and np.abs(w).max() <= 1


def test_a_moved_camera_is_reaimed(tmp_path):
    d = load_design(_write(tmp_path, '[cameras.secondary]\ncentre_mm = [0.0, -300.0, 150.0]\n'))
    cam = d.rig.camera("secondary")
    np.testing.assert_allclose(cam.centre, [0.0, -300.0, 150.0], atol=1e-9)
    uv, _ = cam.project(np.asarray([d.rig.sample.origin]))
    # the sample origin projects to the principal point: the camera looks at it
    np.testing.assert_allclose(uv[0], cam.K[:2, 2], atol=1e-6)


def test_upload_cost_matches_the_emulator_link():
    """The bytes and commands upload_cost counts are those the host really sends to the emulator process
    and receives back (LinkStats), for fresh patterns stored and shown once each."""
    rig = twin.load_rig("mini")
    rng = np.random.default_rng(5)
    levels = rng.integers(0, 256, (3, rig.num_leds, 3), dtype=np.uint8)
    levels[1, rng.random(rig.num_leds) < 0.8] = 0  # a sparse frame: only its changed runs travel
    proc, url = spawn(rig.num_leds, slots=8)
    try:
        with LedController(url, rig.num_leds) as ctl:
            ctl.reset()
            before = (ctl.stats.commands, ctl.stats.bytes_sent, ctl.stats.bytes_received)
            for lv in levels:
                ctl.show(lv)
            got = (ctl.stats.commands - before[0], ctl.stats.bytes_sent - before[1],
                   ctl.stats.bytes_received - before[2])
    finally:
        proc.terminate()
        proc.wait(10)
    cost = upload_cost(levels, 2_000_000, 0.001)
    assert (cost.commands, cost.bytes_out, cost.bytes_back) == got
    assert cost.seconds == pytest.approx((got[1] + got[2]) / 200_000 + got[0] * 0.001, rel=1e-12)


def test_acquisition_time_and_duty_closed_forms():
    e = np.array([[[1e-3, 8e-3], [2e-3, 16e-3]], [[4e-3, 32e-3], [1e-3, 8e-3]]])  # 2 photos, 2 cameras
    # per photo the longer camera's bracket: (0.018 + 2 * 0.01) + (0.036 + 2 * 0.01)
    assert acquisition_time(e, 0.01) == pytest.approx(0.038 + 0.056, rel=1e-12)
    lv = np.zeros((2, 3, 3), np.uint8)
    lv[0, 0] = 255
    lv[1, 0, 1] = 51
    lv[1, 2] = 102
    d = led_duty(lv, np.array([1.0, 3.0]))
    np.testing.assert_allclose(d["peak"], [1.0, 0.0, 0.4])
    np.testing.assert_allclose(d["mean"], [(1.0 + 3 * 0.2) / 4, 0.0, 3 * 0.4 / 4])
    with pytest.raises(ValueError, match="must match"):
        led_duty(lv, np.ones(3))


def test_fixed_and_masked_patterns_in_training(tmp_path):
    """A fixed family stays exactly as given through training (only the decoder learns); LEDs a layout
    leaves off are 0 in the learned patterns and in the exported levels."""
    from reconstruction.network.train import TrainConfig, export_patterns, load_run_model, train
    from twin.capture.pattern_sets import hadamard
    from twin.capture.patterns import save_patterns

    rig = twin.load_rig("mini")
    pf = save_patterns(hadamard(rig, 4), tmp_path / "h.npz")
    cfg = dict(rig="mini", steps=3, batch=16, eval_every=3, checkpoint_every=3, heldout_size=32, patterns_per_view=4)
    train(TrainConfig(**cfg, patterns_file=str(pf)), tmp_path / "fixed", progress=False)
    got = export_patterns(load_run_model(tmp_path / "fixed"), rig)
    np.testing.assert_array_equal(got.levels, hadamard(rig, 4).levels)
    off = (0, 5, 17)
    train(TrainConfig(**cfg, leds_off=off), tmp_path / "masked", progress=False)
    model = load_run_model(tmp_path / "masked")
    assert torch.count_nonzero(model.patterns.weights()[..., list(off)]) == 0
    upper = np.flatnonzero(~np.asarray(rig.is_bottom))
    assert not export_patterns(model, rig).levels[:, upper[list(off)]].any()


def test_design_evaluate_two_designs(tmp_path, capsys):
    for name, family in (("learned-4", "learned"), ("hadamard-4", "hadamard")):
        _write(tmp_path, f'name = "{name}"\n[patterns]\nfamily = "{family}"\ncount = 4\n'
                         '[training]\nsteps = 8\nbatch = 16\nseeds = [0, 1, 2]\n', f"{name}.toml")
    out = tmp_path / "out"
    # --jobs 2: the six training runs in two worker processes first, then the scoring finds them finished
    rc = hemicube.cli.main(["design", "evaluate", str(tmp_path / "learned-4.toml"), str(tmp_path / "hadamard-4.toml"),
                            "-o", str(out), "--no-progress", "--jobs", "2", "--study", str(tmp_path / "s.json")])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "learned-4" in printed and "hadamard-4" in printed and "heldout_eq3" in printed
    res = json.loads((out / "designs.json").read_text())
    assert set(res["how"]) >= {"heldout_eq3", "snr_median", "mux_gain_median", "capture_s", "duty_peak"}
    for row in res["designs"]:
        assert len(row["heldout_eq3_per_seed"]) == 3 and np.isfinite(row["heldout_eq3_per_seed"]).all()
        assert row["heldout_eq3_std"] > 0  # three seeds train three different networks
        assert np.isfinite(row["blind_eq3"]) and row["blind_eq3"] > 0
        for seed in (0, 1, 2):  # each run trained to its budget
            assert json.loads((out / row["design"] / f"seed{seed}" / "metrics.json").read_text())["steps"] == 8
        assert row["snr_median"] > 1 and row["capture_s"] > row["upload_s"] > 0
        assert 0 < row["duty_mean_max"] <= row["duty_peak"] <= 1
    # Hadamard frames drive every LED at full level: peak duty 1
    assert res["designs"][1]["duty_peak"] == 1.0
    # the two worker processes shared the six runs
    assert set(res["trained_by"]) == {f"{d} seed {s}" for d in ("learned-4", "hadamard-4") for s in (0, 1, 2)}
    assert len({r["process"] for r in res["trained_by"].values()}) == 2
    # every seed's held-out curve recorded (at the start and at every tenth of the steps, here every step), and a
    # verdict on the pair that an 8-step budget cannot make "real"
    for row in res["designs"]:
        assert [s for s, _ in row["heldout_curve_per_seed"][0]] == list(range(9))
    (verdict,) = res["verdicts"]
    assert verdict["verdict"] == "not resolved" and verdict["why"] and verdict["text"] in printed
    # the study's record: designs.json's numbers with where they came from, its verdict computed again from them
    study = load_study(tmp_path / "s.json")
    assert json.dumps(study["designs"]) == json.dumps(res["designs"]) and study["study"] == "s" and study["device"] == "cpu"
    assert study["command"] == (f"hemicube design evaluate {tmp_path / 'learned-4.toml'} {tmp_path / 'hadamard-4.toml'} "
                                f"-o {out} --jobs 2")
    assert set(study["software"]) >= {"git_commit", "torch", "warp"} and study["seconds"] > 0
    assert f"  {verdict['text']}" in study_lines(study)
    rows = list(csv.DictReader(open(out / "designs.csv")))
    assert [r["design"] for r in rows] == ["learned-4", "hadamard-4"]
    for f in ("heldout.png", "snr.png", "learned-4/patterns.png", "hadamard-4/patterns.png"):
        assert (out / f).stat().st_size > 1000
    # a bad design among several stops everything before any training, naming the file and field
    bad = _write(tmp_path, '[leds]\noff = [-1]\n', "bad.toml")
    rc = hemicube.cli.main(["design", "evaluate", str(tmp_path / "learned-4.toml"), str(bad), "-o",
                            str(tmp_path / "o2")])
    assert rc == 2 and not (tmp_path / "o2").exists()
    assert "bad.toml: leds.off: LED index -1 is not on rig" in capsys.readouterr().err
    rc = hemicube.cli.main(["design", "evaluate", str(tmp_path / "learned-4.toml"), "-o", str(tmp_path / "o3"),
                            "--maps", "wood", "--maps-resolution", "2"])
    assert rc == 2 and not (tmp_path / "o3").exists()
    assert "maps resolution must be an integer >= 4 texels per side, got 2" in capsys.readouterr().err


def test_a_study_record_is_written_only_where_one_may_be(tmp_path, capsys):
    """--study names a .json file that is absent or an earlier study's record (which a study run again replaces);
    anything else stops the command before any work, in one line. A record is read back checked."""
    from hemicube.design import _study_path

    design = _write(tmp_path, 'name = "l"\n[patterns]\nfamily = "learned"\ncount = 2\n')
    (tmp_path / "notes.json").write_text('{"mine": 1}')
    for bad, words in (("notes.json", "exists and is not a study record"), ("s.txt", "must name a .json file"),
                       ("nowhere/s.json", "does not exist")):
        rc = hemicube.cli.main(["design", "evaluate", str(design), "-o", str(tmp_path / "o"), "--study",
                                str(tmp_path / bad)])
        err = capsys.readouterr().err
        assert rc == 2 and words in err and err.strip().count("\n") == 0 and not (tmp_path / "o").exists()
    assert json.loads((tmp_path / "notes.json").read_text()) == {"mine": 1}
    (tmp_path / "old.json").write_text(json.dumps({"format": "hemicube-design-study", "version": 1}))
    assert _study_path(tmp_path / "old.json") == tmp_path / "old.json"
    with pytest.raises(ValueError, match="needs its designs' rows"):
        load_study(tmp_path / "old.json")
    with pytest.raises(ValueError, match="not a design study record"):
        load_study(tmp_path / "notes.json")


def test_design_evaluate_maps_through_the_twin(tmp_path, capsys):
    """--maps: a held-back sample (a folder of OpenSVBRDF maps) captured with the design's patterns and
    reconstructed with its network; the map errors and render SSIM land in the table. An 8-step network
    reconstructs badly: this checks the path and the figures' ranges, not their quality."""
    from hemicube.design import MAP_METRICS
    from twin.materials.samples import load_sample, write_maps

    write_maps(load_sample("wood@9101", 32), tmp_path / "wood")
    d = _write(tmp_path, 'name = "m4"\n[patterns]\ncount = 4\n[training]\nsteps = 8\nbatch = 16\nseeds = [0]\n')
    out = tmp_path / "out"
    assert hemicube.cli.main(["design", "evaluate", str(d), "-o", str(out), "--maps", str(tmp_path / "wood"),
                              "--maps-resolution", "16"]) == 0
    assert "maps_render_ssim" in capsys.readouterr().err  # the progress lines name each sample's figures
    row = json.loads((out / "designs.json").read_text())["designs"][0]
    assert all(np.isfinite(row[k]) and row[k] >= 0 for k in MAP_METRICS)
    assert 0 < row["maps_render_ssim"] <= 1
    per = row["maps_per_sample"][str(tmp_path / "wood")]
    assert row["maps_goals_missed"] == len(per["goals_missed"])
    assert (out / "m4" / "maps" / "00_wood" / "report" / "metrics.json").is_file()
    assert "texture grid 16^2" in (out / "m4" / "maps" / "00_wood" / "report" / "report.md").read_text()
    assert "maps_alpha_pct" in next(csv.DictReader(open(out / "designs.csv")))


def test_database_like_training_distribution():
    """'suite:SEEDS' draws each texel's four material numbers together, as one texel of the suite's maps
    (clipped to the network's ranges), deterministically; a bad spec fails at once."""
    from reconstruction.network.data import SamplingConfig, material_table, sample_parameters
    from twin.materials.samples import SUITE, load_sample

    cfg = SamplingConfig(materials="suite:3")
    table = material_table(cfg)
    assert table.shape == (len(SUITE) * 64 * 64, 4)
    m = load_sample(f"{SUITE[0]}@3", 64)
    np.testing.assert_allclose(table[:10, 0], m.rho_d.reshape(-1, 3).mean(1)[:10], rtol=1e-6)
    assert table[:, 1].max() <= cfg.rho_s_range[1] and table[:, 2:].min() >= cfg.alpha_range[0]
    rig = twin.load_rig("mini")
    draws = [sample_parameters(512, cfg, rig, torch.Generator().manual_seed(7)) for _ in range(2)]
    for k in ("rho_d", "alpha_x"):
        assert torch.equal(draws[0][k], draws[1][k])
    got = torch.stack([draws[0]["rho_d"][:, 0], draws[0]["rho_s"][:, 0], draws[0]["alpha_x"], draws[0]["alpha_y"]], 1)
    rows = {tuple(r) for r in np.float32(table).tolist()}
    assert all(tuple(r) in rows for r in got.numpy().tolist())  # whole rows: the correlations are kept
    for bad in ("suite:", "suite:x", "atlas:1", "maps:/nonexistent/folder"):
        with pytest.raises(ValueError, match="SamplingConfig.materials"):
            SamplingConfig(materials=bad)


def test_design_distributions(tmp_path):
    d = load_design(_write(tmp_path, '[training]\ndistribution = "suite"\n'))
    assert d.training.materials(d.training.distribution) == "suite:0,1,2"
    # tested by default on the training distribution, for "suite" on compositions held back from training
    held_back = d.training.materials(d.training.test_distribution, test=True)
    assert held_back.startswith("suite:") and not set(held_back[6:].split(",")) & {"0", "1", "2"}
    with pytest.raises(DesignError, match=r"training\.test_distribution: .* holds no folder of OpenSVBRDF maps"):
        load_design(_write(tmp_path, '[training]\ntest_distribution = "maps:nowhere"\n'))


def test_any_pattern_count_through_capture_and_reconstruction(tmp_path, capsys):
    """A design's K = 4 patterns (8 photos per view): `hemicube design optimise` trains them, the capture
    plan takes them (lines, bottom, uniform shift after them), and the pipeline decodes with that network."""
    from reconstruction.output import MEASUREMENTS
    from twin.capture.plan import REFERENCE_INDICES, PlanIndices, indices_of
    from twin.capture.session import CaptureSession

    d = _write(tmp_path, '[patterns]\ncount = 4\n[training]\nsteps = 10\nbatch = 16\nseeds = [4]\n')
    assert hemicube.cli.main(["design", "optimise", str(d), "-o", str(tmp_path / "opt"), "--no-progress"]) == 0
    run = tmp_path / "opt" / "run"
    assert "hemicube capture --patterns" in capsys.readouterr().out
    cap, rec = tmp_path / "cap", tmp_path / "rec"
    assert hemicube.cli.main(["capture", "--rig", "mini", "--sample", "ramps", "--sample-resolution", "32", "--patterns",
                              str(run / "patterns.npz"), "-o", str(cap), "--no-progress"]) == 0
    ix = indices_of(CaptureSession.open(cap))
    assert ix == PlanIndices(8) and (ix.lines.start, ix.uniform) == (8, 73)
    assert REFERENCE_INDICES.uniform == 129  # the reference's layout is unchanged for K = 32
    assert hemicube.cli.main(["reconstruct", str(cap), "--network", str(run), "--resolution", "12", "-o", str(rec),
                              "--no-progress"]) == 0
    with np.load(rec / MEASUREMENTS) as meas:
        assert meas["learned_photos"].shape == (144, 2, 8, 3) and meas["learned"].shape == (144, 2, 4)
    # a network of another K refuses the capture, naming the mismatch
    assert hemicube.cli.main(["reconstruct", str(cap), "-o", str(tmp_path / "rec2"), "--no-progress"]) == 2
    assert "are not this network's patterns" in capsys.readouterr().err
