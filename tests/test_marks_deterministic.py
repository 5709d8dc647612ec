"""The same scan gives the same result, run after run (nothing in the fits may depend on
memory layout or thread timing)."""
import numpy as np

from softplot.marks.measure import _grad_magnitude


def test_gradient_magnitude_is_the_same_on_every_call():
    """OpenCV's magnitude rounded the last bit differently from call to call on the same
    data; the prior weights of every fit over a scene edge are built on this gradient."""
    rng = np.random.default_rng(1)
    for shape in ((8 * 53, 23), (1000, 61)):
        img = rng.random(shape).astype(np.float32)
        first = _grad_magnitude(img.copy())
        for _ in range(30):
            assert np.array_equal(_grad_magnitude(img.copy()), first)
        assert np.isfinite(first).all() and first.min() >= 0


def test_a_busy_scan_is_measured_the_same_twice():
    """Sweep render 145 (Rollei, 485 dpi, busy scene, blur 2.35 px, JPEG q47): its fits on
    conflicting scene content used to amplify last-bit differences into crosses 0.4-2.9 px
    apart and 13-18 gross crosses from one run to the next."""
    from softplot.synthetic.sweep import make_case, run_case

    case = make_case(145)
    _, a = run_case(case)
    _, b = run_case(case)
    assert a is not None and b is not None
    assert a.status == b.status
    np.testing.assert_array_equal(a.xy, b.xy)
    np.testing.assert_array_equal(a.cov, b.cov)
