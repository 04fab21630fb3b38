"""The open-world correction: its integration is kinematics, its selection finds a planted term and nothing in noise,
and diagnose.py calls physics outside its library `unexplained`, where it acts."""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnose import SMALL, concealed, diagnose

from contactbench.diagnosis import open_world
from contactbench.diagnosis.phases import FREE, PHASES, SLIDING

DT = 0.01


def test_a_constant_acceleration_integrates_to_half_a_t_squared_on_the_frame_grid():
    m, length, k = 3, 16, 1
    features = np.zeros((m, length, k, len(open_world.FEATURES)))
    features[..., 0] = 1.0  # the constant
    phases = np.full((m, length, k), FREE)
    widths = np.array([0.1])
    dictionary = open_world.integrate(features, phases, DT, widths)
    j = np.arange(1, length + 1)
    # semi-implicit Euler: after j frames of acceleration a, x_j = a dt^2 j (j + 1) / 2
    np.testing.assert_allclose(dictionary.angular[0, :, 0, FREE, 0], DT**2 * j * (j + 1) / 2)
    np.testing.assert_allclose(dictionary.linear[0, :, 0, FREE, 0], DT**2 * j * (j + 1) / 2 / 0.05)
    assert not dictionary.linear[..., SLIDING, :].any()  # gated: no sliding frame, no sliding column


def planted(rng, coefficient=None, output=1):
    m, length, k = 200, 16, 1
    features = rng.normal(size=(m, length, k, len(open_world.FEATURES)))
    phases = rng.choice([FREE, SLIDING], size=(m, length, k))
    dictionary = open_world.integrate(features, phases, DT, np.array([0.1]))
    noise = 1e-3 * rng.normal(size=(m, length, k, 6))
    residuals = noise.copy()
    if coefficient is not None:  # the simulator misses a sliding-phase force along `output` proportional to v_x
        residuals[..., output] -= coefficient * dictionary.column(output, SLIDING, open_world.FEATURES.index("v_x"))
    return dictionary, residuals


def test_forward_selection_finds_a_planted_term_and_nothing_in_noise():
    rng = np.random.default_rng(0)
    dictionary, residuals = planted(rng, coefficient=-2.5)
    found = open_world.fit_correction(dictionary, residuals, 1.0, 4, np.ones(len(residuals), bool))
    assert found.described()[0] == {
        "output": "linear_y",
        "phase": PHASES[SLIDING],
        "depends_on": "v_x",
        "coefficient": pytest.approx(-2.5, rel=0.02),
    }
    after = open_world.corrected(residuals, found, dictionary)
    assert np.mean(after**2) < 0.1 * np.mean(residuals**2)
    dictionary, noise = planted(np.random.default_rng(1))
    assert open_world.fit_correction(dictionary, noise, 1.0, 4, np.ones(len(noise), bool)).terms == []


def test_physics_outside_the_library_is_unexplained_and_located_where_it_acts(tmp_path):
    turning = concealed(tmp_path, "coriolis", "coriolis", 2.0)
    verdict, document = diagnose(turning, tmp_path / "out", tmp_path, SMALL)
    assert verdict == "unexplained" and document["effects"] == []
    found = document["open_world"]
    assert found["passes"] and found["heldout"]["confirmed"]
    assert found["located"]["phase"] in ("free", "sliding", "rolling")
    assert found["located"]["output"] in ("linear_x", "linear_y")
    report = (tmp_path / "out" / "report.md").read_text()
    assert "Something the library does not list is missing" in report and "| linear_" in report


def test_the_contact_normal_is_left_to_the_contact_model_but_not_in_free_flight():
    # engines' soft contacts sink and lift a touching body differently with nothing concealed: not physics nobody listed
    dictionary, residuals = planted(np.random.default_rng(2), coefficient=-2.5, output=open_world.NORMAL)
    found = open_world.fit_correction(dictionary, residuals, 1.0, 4, np.ones(len(residuals), bool))
    assert all(output != open_world.NORMAL or phase == FREE for output, phase, _ in found.terms)
    rng = np.random.default_rng(3)
    dictionary, residuals = planted(rng)
    residuals[..., open_world.NORMAL] -= 2.5 * dictionary.column(open_world.NORMAL, FREE, 0)  # a weaker gravity
    found = open_world.fit_correction(dictionary, residuals, 1.0, 4, np.ones(len(residuals), bool))
    assert (open_world.NORMAL, FREE, 0) in found.terms
