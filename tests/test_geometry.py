import numpy as np
import pytest

from mgso import geometry as g


def random_rotation(rng):
    return g.so3_exp(rng.normal(size=3))


def test_so3_exp_log_roundtrip(rng):
    for scale in [1e-9, 1e-5, 0.3, 2.0, np.pi - 1e-6]:
        w = rng.normal(size=3)
        w = w / np.linalg.norm(w) * scale
        R = g.so3_exp(w)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(g.so3_exp(g.so3_log(R)), R, atol=1e-9)
    # exactly pi: the axis is recovered up to sign, and exp gives the same rotation back
    R = g.so3_exp(np.array([0.0, np.pi, 0.0]))
    assert np.allclose(g.so3_exp(g.so3_log(R)), R, atol=1e-9)


def test_so3_exp_matches_series(rng):
    from scipy.linalg import expm

    w = rng.normal(size=3)
    assert np.allclose(g.so3_exp(w), expm(g.hat(w)), atol=1e-12)


def test_se3_exp_matches_matrix_exponential(rng):
    from scipy.linalg import expm

    xi = rng.normal(size=6)
    m = np.zeros((4, 4))
    m[:3, :3] = g.hat(xi[3:])
    m[:3, 3] = xi[:3]
    assert np.allclose(g.se3_exp(xi), expm(m), atol=1e-10)
    assert np.allclose(g.se3_log(g.se3_exp(xi)), xi, atol=1e-10)


def test_se3_batch_and_inverse(rng):
    xis = rng.normal(size=(5, 6))
    Ts = g.se3_exp(xis)
    assert Ts.shape == (5, 4, 4)
    for xi, T in zip(xis, Ts):
        assert np.allclose(T, g.se3_exp(xi))
    assert np.allclose(g.se3_inverse(Ts) @ Ts, np.eye(4), atol=1e-12)


def test_se3_adjoint(rng):
    T = g.se3_exp(rng.normal(size=6))
    xi = rng.normal(size=6) * 0.1
    lhs = T @ g.se3_exp(xi) @ g.se3_inverse(T)
    assert np.allclose(lhs, g.se3_exp(g.se3_adjoint(T) @ xi), atol=1e-10)


def test_interpolate_endpoints_and_midpoint(rng):
    T0 = g.se3_exp(rng.normal(size=6))
    T1 = T0 @ g.se3_exp(np.array([0.2, 0.0, 0.0, 0.0, 0.0, 0.4]))
    assert np.allclose(g.se3_interpolate(T0, T1, 0.0), T0)
    assert np.allclose(g.se3_interpolate(T0, T1, 1.0), T1, atol=1e-12)
    mid = g.se3_interpolate(T0, T1, 0.5)
    assert np.allclose(mid, T0 @ g.se3_exp(np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.2])), atol=1e-12)


def test_sim3_exp_log_roundtrip(rng):
    from scipy.linalg import expm

    for xi in [rng.normal(size=7), np.r_[rng.normal(size=6), 0.0], np.r_[rng.normal(size=3), 0, 0, 0, 0.5]]:
        S = g.sim3_exp(xi)
        m = np.zeros((4, 4))
        m[:3, :3] = g.hat(xi[3:6]) + xi[6] * np.eye(3)
        m[:3, 3] = xi[:3]
        assert np.allclose(S, expm(m), atol=1e-10)
        assert np.allclose(g.sim3_log(S), xi, atol=1e-9)
        assert np.allclose(g.sim3_inverse(S) @ S, np.eye(4), atol=1e-10)


def test_quaternion_orders(rng):
    R = random_rotation(rng)
    q_xyzw = g.matrix_to_quat_xyzw(R)
    q_wxyz = g.matrix_to_quat_wxyz(R)
    assert q_xyzw[3] >= 0 and q_wxyz[0] >= 0
    assert np.allclose(q_xyzw, np.r_[q_wxyz[1:], q_wxyz[0]])
    assert np.allclose(g.quat_xyzw_to_matrix(q_xyzw), R, atol=1e-12)
    assert np.allclose(g.quat_wxyz_to_matrix(q_wxyz), R, atol=1e-12)
    # 90 degrees about z: (x,y,z,w) = (0, 0, sin 45, cos 45)
    Rz = g.so3_exp([0, 0, np.pi / 2])
    assert np.allclose(g.matrix_to_quat_xyzw(Rz), [0, 0, np.sqrt(0.5), np.sqrt(0.5)])
    # all the branches of Shepperd's method
    for w in ([np.pi * 0.999, 0, 0], [0, np.pi * 0.999, 0], [0, 0, np.pi * 0.999]):
        Rb = g.so3_exp(w)
        assert np.allclose(g.quat_wxyz_to_matrix(g.matrix_to_quat_wxyz(Rb)), Rb, atol=1e-12)


def test_orthonormalize_fixes_round_off(rng):
    R = random_rotation(rng)
    noisy = R + 4e-4 * rng.normal(size=(3, 3))
    Ro = g.orthonormalize(noisy)
    assert np.allclose(Ro @ Ro.T, np.eye(3), atol=1e-12)
    assert np.linalg.norm(Ro - R) < 2e-3


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_transform(rng, with_scale):
    src = rng.normal(size=(50, 3))
    R = random_rotation(rng)
    t = rng.normal(size=3)
    s = 2.7 if with_scale else 1.0
    dst = s * src @ R.T + t
    al = g.umeyama_alignment(src, dst, with_scale=with_scale)
    assert np.allclose(al.rotation, R, atol=1e-10)
    assert np.allclose(al.translation, t, atol=1e-10)
    assert np.isclose(al.scale, s)
    assert np.allclose(al.apply_points(src), dst, atol=1e-10)


def test_umeyama_rejects_bad_input():
    with pytest.raises(ValueError, match="at least 3"):
        g.umeyama_alignment(np.zeros((2, 3)), np.zeros((2, 3)), True)
    with pytest.raises(ValueError, match="same shape"):
        g.umeyama_alignment(np.zeros((4, 3)), np.zeros((5, 3)), True)


def test_se3_renormalize_stops_the_doubling_of_round_off():
    """Constant-motion guesses compose the last two poses each frame: without renormalisation the rotation's
    departure from orthonormal roughly doubles a frame (it reached 1e-2 after 40 frames in the odometry)."""
    from mgso.geometry import se3_exp, se3_inverse, se3_renormalize

    rng = np.random.default_rng(3)
    step = se3_exp(rng.normal(scale=0.05, size=6))
    step[:3, :3] += 1e-12 * rng.normal(size=(3, 3))        # round-off
    def err(T):
        return np.abs(T[:3, :3] @ T[:3, :3].T - np.eye(3)).max()

    raw, fixed = [np.eye(4), step], [np.eye(4), step]
    for _ in range(20):
        raw.append(raw[-1] @ se3_inverse(raw[-2]) @ raw[-1])
        fixed.append(se3_renormalize(fixed[-1] @ se3_inverse(fixed[-2]) @ fixed[-1]))
    assert not err(raw[-1]) < 1e-6                                  # the failure this guards against is real
    assert err(fixed[-1]) < 1e-12
    np.testing.assert_allclose(se3_renormalize(fixed[-1]), fixed[-1], atol=1e-12)   # idempotent


def test_single_pose_paths_equal_the_batched_ones():
    """se3_exp / se3_log take a scalar-arithmetic path for one vector / one pose (the tracker calls them dozens of
    times a frame); it must agree with the batched NumPy path, small angles (series), large ones and near pi."""
    rng = np.random.default_rng(11)
    xis = [rng.normal(size=6) * s for s in (1e-8, 1e-5, 1e-3, 0.3, 2.0) for _ in range(50)]
    xis += [np.r_[rng.normal(size=3), (np.pi - 1e-4) * a / np.linalg.norm(a)] for a in rng.normal(size=(20, 3))]
    for xi in xis:
        T1 = g.se3_exp(xi)
        np.testing.assert_allclose(T1, g.se3_exp(xi[None])[0], rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(g.se3_log(T1), g.se3_log(T1[None])[0], rtol=1e-9, atol=1e-11)


def _so3_log_array_form(R):
    """so3_log as it was written with NumPy calls on each 3x3 (until 2026-12-02): the scalar form must give the same
    bits (the odometry's deterministic runs are compared bit for bit)."""
    out = np.empty((len(R), 3))
    for i, r in enumerate(R):
        cos_t = np.clip((np.trace(r) - 1.0) * 0.5, -1.0, 1.0)
        theta = np.arccos(cos_t)
        if theta < 1e-4:
            out[i] = g.vee(r) * (1.0 + theta * theta / 6.0)
        elif np.pi - theta < 1e-3:
            out[i] = g.so3_log(r)  # the near-pi branch is the same code in both
        else:
            out[i] = g.vee(r) * (theta / np.sin(theta))
    return out


def test_so3_log_scalar_form_gives_the_array_form_s_bits(rng):
    w = np.concatenate([rng.normal(0, 1.0, (3000, 3)), rng.normal(0, 1e-5, (500, 3)),   # general, near 0
                        rng.normal(0, 0.05, (500, 3))])
    axis = rng.normal(0, 1, (200, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    w = np.concatenate([w, axis * (np.pi - rng.uniform(0, 2e-3, (200, 1)))])          # near pi
    R = g.orthonormalize(g.so3_exp(w)) + rng.normal(0, 1e-12, (len(w), 3, 3))          # round-off off SO(3)
    got = g.so3_log(R)
    np.testing.assert_array_equal(got.view(np.int64), _so3_log_array_form(R).view(np.int64))
    well = np.linalg.norm(w, axis=1) < 2.5  # (towards pi the log is ill-conditioned)
    np.testing.assert_allclose(g.so3_exp(got[well]), R[well], atol=1e-9)
