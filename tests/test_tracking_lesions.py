"""The lesion prediction's uncertainty model (regtrack.tracking.lesions), known answers."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from regtrack.tracking.config import TrackingConfig
from regtrack.tracking.uncertainty import angular_sigma, prediction_sigma


class Parabola:
    """F(theta) = a (theta - theta0)^2 + c over K samples: a least-squares objective."""

    def __init__(self, a, theta0, c, k):
        self.a, self.theta0, self.c = a, theta0, c
        self.virtual = np.zeros((k, 2))

    def __call__(self, theta):
        return self.a * (theta - self.theta0) ** 2 + self.c


def test_angular_sigma_of_a_quadratic_objective():
    """F'' = 2a exactly (central differences are exact on a parabola), s^2 = c / (K - 1):
    sigma^2 = 2 s^2 / F'' * L_c / h = c / ((K - 1) a) * L_c / h."""
    a, c, k = 40.0, 300.0, 401
    got = angular_sigma(Parabola(a, 2.0, c, k), 2.0, correlation_mm=10.0, spacing_mm=0.5)
    assert got == pytest.approx(math.sqrt(c / ((k - 1) * a) * 20.0), rel=1e-9)
    # samples closer than the correlation length are not independent: never deflated
    got1 = angular_sigma(Parabola(a, 2.0, c, k), 2.0, correlation_mm=0.1, spacing_mm=0.5)
    assert got1 == pytest.approx(math.sqrt(c / ((k - 1) * a)), rel=1e-9)


def test_flat_objective_gives_the_cap():
    assert angular_sigma(Parabola(0.0, 0.0, 5.0, 10), 0.0, correlation_mm=10, spacing_mm=0.5,
                         cap_deg=7.0) == 7.0


def test_lesion_sigma_terms_add_in_quadrature():
    cfg = TrackingConfig(min_residual_mm=0.5, material_rel=0.1)
    s, t = prediction_sigma(residual_mm=0.2, r_mm=60.0, theta_sigma_deg=1.0, shift_mm=8.0,
                        D=0.4, sigma_D=0.04, config=cfg)
    rot = 60.0 * math.radians(1.0)               # 1.047 mm
    model = 8.0 * math.hypot(0.04 / 0.4, 0.1)    # 1.131 mm
    assert t == pytest.approx({"registration_residual": 0.2, "rotation": rot, "model": model,
                               "nipple": 0.0})
    assert s == pytest.approx(math.sqrt(0.5 ** 2 + rot ** 2 + model ** 2))  # residual floored
    # the nipple term joins in quadrature
    s2, t2 = prediction_sigma(residual_mm=0.2, r_mm=60.0, theta_sigma_deg=1.0, shift_mm=8.0,
                              D=0.4, sigma_D=0.04, nipple_mm=2.0, config=cfg)
    assert t2["nipple"] == 2.0
    assert s2 == pytest.approx(math.sqrt(s ** 2 + 4.0))


def test_the_nipple_term_is_the_registrations_answer_to_a_moved_nipple():
    """A circular skin line (radius rho = 60 mm, centre c): the detector's nipple is the
    middle of the run within delta = 1 mm of the farthest point, half-length
    u = rho arccos(1 - delta / rho).  Moving it by h = u / sqrt 3 along the run, the
    registration turns the circle back onto itself by about +-h / rho, so the predicted
    centre moves only by h^2 / (2 rho) towards the chest wall for either sign: its first-
    order spread |p+ - p-| / 2 vanishes, while a point at the nipple moves by h (6.3 mm
    here).  Tolerances: the open arc, the 0.1 deg sampling of the circle and the
    golden-section search leave effects of hundredths of a millimetre."""
    from regtrack.imaging.mammogram.nipple import detect_nipple
    from regtrack.registration import RegistrationConfig, align
    from regtrack.tracking.uncertainty import NippleMoves
    from regtrack.views import MammogramView

    rho, c = 60.0, np.array([0.0, 100.0])
    phi = np.deg2rad(np.linspace(-80.0, 80.0, 1601))
    skin = c + rho * np.stack([np.cos(phi), np.sin(phi)], 1)
    nip, info = detect_nipple(skin, delta_mm=1.0)
    u = rho * math.acos(1.0 - 1.0 / rho)
    assert info["tangential_uncertainty_mm"] == pytest.approx(u, abs=0.2)
    real = MammogramView("CC", "R", skin, nip, meta={"nipple": info})
    virtual = MammogramView("CC", "R", skin.copy(), nip.copy())
    al = align(real, virtual, config=RegistrationConfig(use_tumour=False))
    moves = NippleMoves.from_alignment(al, real)
    h = info["tangential_uncertainty_mm"] / math.sqrt(3.0)
    at_centre, at_nipple = moves.sigma(np.vstack([c, nip]))
    assert at_nipple == pytest.approx(h, rel=0.02)
    assert at_centre < 0.1
    for (n, th), sign in zip(moves.moved, (1.0, -1.0)):   # turned back by h / rho
        assert th == pytest.approx(sign * math.degrees(h / rho), rel=0.02)
    # a nipple given on the image has no run: no term
    given = MammogramView("CC", "R", skin, nip, meta={"nipple": {"method": "given (nipple_px)"}})
    assert NippleMoves.from_alignment(al, given) is None


def test_nipple_run_from_the_real_view():
    from regtrack.tracking.uncertainty import nipple_run

    detected = SimpleNamespace(meta={"nipple": {"method": "detected", "tangential_uncertainty_mm": 4.5}})
    given = SimpleNamespace(meta={"nipple": {"method": "given (nipple_px)", "confidence": 1.0}})
    assert nipple_run(detected) == 4.5
    assert nipple_run(given) == 0.0 and nipple_run(SimpleNamespace(meta={})) == 0.0


def test_view_mode():
    from regtrack.pipeline.stages import view_mode
    from regtrack.registration.config import RegistrationConfig

    with_t = SimpleNamespace(tumour_contours=[np.zeros((4, 2))])
    without = SimpleNamespace(tumour_contours=[])
    cfg = RegistrationConfig()
    assert view_mode(with_t, with_t, cfg) == ("paper", None)
    assert view_mode(without, with_t, cfg)[0] == "tracking"
    assert view_mode(with_t, without, cfg)[0] == "tracking"
    mode, why = view_mode(with_t, with_t, RegistrationConfig(use_tumour=False))
    assert mode == "tracking" and "use_tumour" in why
