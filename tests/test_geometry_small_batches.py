"""quat_multiply and quat_to_matrix take one numpy form for a few quaternions and another
for large batches (agent.geometry._SMALL), matrix_to_quat and quat_to_rotvec a float form
for one: each must give the same results as the batch. quat_rotate's cross products must
give np.cross's."""

from __future__ import annotations

import numpy as np

from agent import geometry as geo


def test_small_and_large_batch_forms_agree():
    rng = np.random.default_rng(7)
    a = rng.normal(size=(200, 4))
    b = rng.normal(size=(200, 4))
    assert a.size > geo._SMALL  # the whole batch takes the large form, each row the small one
    big_mul, big_rot = geo.quat_multiply(a, b), geo.quat_to_matrix(a)
    for i in range(len(a)):
        np.testing.assert_allclose(geo.quat_multiply(a[i], b[i]), big_mul[i], rtol=0,
                                   atol=1e-14)
        np.testing.assert_array_equal(geo.quat_to_matrix(a[i]), big_rot[i])
    small = geo.quat_multiply(a[:3], b[:3])
    np.testing.assert_allclose(small, big_mul[:3], rtol=0, atol=1e-14)
    assert geo.quat_multiply(a[0], b[:3]).shape == (3, 4)  # broadcasting kept


def test_hamilton_product_of_basis_quaternions():
    i, j, k, one = np.eye(4)
    np.testing.assert_array_equal(geo.quat_multiply(i, j), k)
    np.testing.assert_array_equal(geo.quat_multiply(j, i), -k)
    np.testing.assert_array_equal(geo.quat_multiply(i, i), -one)
    np.testing.assert_array_equal(geo.quat_to_matrix(one), np.eye(3))


def test_one_matrix_and_one_quaternion_equal_the_batch_to_the_bit():
    rng = np.random.default_rng(11)
    q = rng.normal(size=(3000, 4))
    unit = q / np.linalg.norm(q, axis=1, keepdims=True)
    R = geo.quat_to_matrix(unit)
    # every pivot of Shepperd's method, half-turns, the identity and tiny turns, off-unit
    # matrices and quaternions, a negative w
    R = np.concatenate([R, R + rng.normal(size=R.shape) * 1e-3, np.eye(3)[None],
                        np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None],
                        np.diag([-1.0, -1, 1])[None], geo.rodrigues(np.array([[1e-10, 0, 0]]))])
    batch = geo.matrix_to_quat(R)
    for i in range(len(R)):
        assert geo.matrix_to_quat(R[i]).tobytes() == batch[i].tobytes()
    few = geo._FEW_MATRICES
    assert geo.matrix_to_quat(R[:few]).tobytes() == batch[:few].tobytes()
    assert geo.matrix_to_quat(R[-few:].reshape(2, -1, 3, 3)).tobytes() == batch[-few:].tobytes()
    assert geo.matrix_to_quat(R[:0]).shape == (0, 4)
    q = np.concatenate([unit, q, -unit, [[0, 0, 0, 1.0], [1e-12, 0, 0, 1], [1.0, 0, 0, 0]]])
    rotvecs = geo.quat_to_rotvec(q)
    for i in range(len(q)):
        assert geo.quat_to_rotvec(q[i]).tobytes() == rotvecs[i].tobytes()


def test_rotations_equal_np_cross_to_the_bit():
    """quat_rotate's cross products (per component, without np.cross's axis handling) give
    np.cross's bits, also broadcast, for zeros of either sign, parallel vectors and
    far-apart magnitudes."""
    rng = np.random.default_rng(5)

    def reference(q, v):
        u, w = q[..., :3], q[..., 3:4]
        t = 2.0 * np.cross(u, v)
        return v + w * t + np.cross(u, t)

    for shape in [(), (1,), (5,), (2, 3), (300,)]:
        for scale in (1e-300, 1.0, 1e200):
            q = rng.normal(size=(*shape, 4))
            q /= np.linalg.norm(q, axis=-1, keepdims=True)
            v = rng.normal(size=(*shape, 3)) * scale
            assert geo.quat_rotate(q, v).tobytes() == reference(q, v).tobytes()
    q, v = rng.normal(size=4), rng.normal(size=(7, 3))
    assert geo.quat_rotate(q, v).tobytes() == reference(q, v).tobytes()  # broadcast
    for a, b in [(np.zeros(3), np.ones(3)), (np.array([1.0, -0.0, 0.0]), np.array([2.0, 0, 0])),
                 (np.array([-0.0, 0, 1]), np.array([0.0, -1, 0])), (np.ones((2, 3)), np.ones(3))]:
        assert geo.cross(a, b).tobytes() == np.cross(a, b).tobytes()
