"""ProMP (paper 003 Eq. 1-4): basis, moments, sampling, conditioning, EM learning, file I/O."""
import json
import os

import jsonschema
import numpy as np
import pytest

from cdmp_ros.core.errors import PrimitiveFileError, ValidationError
from cdmp_ros.core.promp.promp import ProMP, RbfBasis
from cdmp_ros.core.primitive_io import primitive_from_dict, primitive_to_dict, promp_from_dict
from cdmp_ros.core.promp.primitive_file import base64_length, promp_body


def _random_promp(rng, D=2, M=6):
    A = rng.standard_normal((D * M, D * M))
    return ProMP(D, RbfBasis.uniform(M), rng.standard_normal(D * M), A @ A.T / (D * M) + 0.1
                 * np.eye(D * M))


def test_basis_normalised_and_derivatives_match_finite_differences():
    b = RbfBasis.uniform(8)
    s = np.linspace(0, 1, 37)
    assert np.allclose(b.features(s).sum(axis=1), 1.0, atol=1e-12)
    h = 1e-5
    d1 = (b.features(s + h) - b.features(s - h)) / (2 * h)
    assert np.allclose(b.features(s, 1), d1, rtol=1e-6, atol=1e-6)
    d2 = (b.features(s + h, 1) - b.features(s - h, 1)) / (2 * h)
    assert np.allclose(b.features(s, 2), d2, rtol=1e-5, atol=1e-5)


def test_moments_closed_form_and_monte_carlo(rng):
    p = _random_promp(rng)
    s = np.array([0.1, 0.5, 0.9])
    phi = p.basis.features(s)
    W = p.mean_w.reshape(2, -1)
    assert np.allclose(p.mean(s), phi @ W.T)
    C = p.joint_cov(s)
    M = p.n_basis
    # cross-time cross-joint entry: Cov[z_{t0}[0], z_{t2}[1]] = phi_0^T Sigma_(0,1) phi_2
    assert np.isclose(C[0 * 2 + 0, 2 * 2 + 1], phi[0] @ p.cov_w[:M, M:] @ phi[2])
    assert np.allclose(np.array([C[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(3)]),
                       p.cov(s))
    Y = p.sample_trajectories(s, 200000, rng).reshape(200000, -1)
    assert np.allclose(Y.mean(axis=0), p.mean(s).ravel(), atol=0.02)
    assert np.allclose(np.cov(Y.T), C, atol=0.03)


def test_conditioning_matches_gaussian_conditioning_of_the_trajectory(rng):
    p = _random_promp(rng)
    s_obs = np.array([0.3])
    y_obs = np.array([[0.7, -1.2]])
    q = p.condition(s_obs, y_obs, var=1e-4)
    # closed form in trajectory space: joint Gaussian of (z_0.3, z_0.8)
    s = np.array([0.3, 0.8])
    m = p.mean(s).ravel()
    C = p.joint_cov(s)
    Coo = C[:2, :2] + 1e-4 * np.eye(2)
    K = C[2:, :2] @ np.linalg.inv(Coo)
    m_c = m[2:] + K @ (y_obs.ravel() - m[:2])
    C_c = C[2:, 2:] - K @ C[:2, 2:]
    assert np.allclose(q.mean([0.8]).ravel(), m_c, atol=1e-9)
    assert np.allclose(q.cov([0.8])[0], C_c, atol=1e-9)
    assert np.allclose(q.mean(s_obs), y_obs, atol=2e-3)
    # velocity via-point, one dimension unobserved (NaN)
    r = p.condition([0.5], [[np.nan, np.nan]], yd=[[2.0, np.nan]], var_yd=1e-8)
    assert np.isclose(r.mean([0.5], derivative=1)[0, 0] / p.duration, 2.0, atol=1e-4)


def test_em_learns_mean_and_covariance_from_demos_of_different_lengths(rng):
    basis = RbfBasis.uniform(6)
    true = ProMP(2, basis, rng.standard_normal(12), 0.05 * np.eye(12))
    demos = []
    for i in range(60):
        n = 30 + 7 * (i % 5)
        T = np.linspace(0, 2.0 + 0.1 * (i % 3), n)
        w = true.sample_weights(1, rng)[0]
        Y = basis.features((T - T[0]) / (T[-1] - T[0])) @ w.reshape(2, -1).T
        demos.append((T, Y + 1e-3 * rng.standard_normal(Y.shape)))
    p = ProMP.fit(demos, basis, prior_strength=1e-3)
    s = np.linspace(0, 1, 11)
    assert np.allclose(p.mean(s), true.mean(s), atol=0.08)
    assert np.allclose(p.cov(s), true.cov(s), atol=0.02)
    assert np.all(p.sigma_y < 1e-4)


def test_em_with_fewer_demos_than_weights_is_positive_definite(rng):
    basis = RbfBasis.uniform(15)
    T = np.linspace(0, 1, 50)
    demos = [(T, np.c_[np.sin(3 * T + 0.1 * i), np.cos(2 * T) * (1 + 0.1 * i)])
             for i in range(3)]
    p = ProMP.fit(demos, basis)
    assert np.all(np.linalg.eigvalsh(p.cov_w) > 0)
    assert np.allclose(p.mean(T[::7]), np.mean([Y for _, Y in demos], axis=0)[::7], atol=0.02)


def test_promp_dict_round_trip_and_schema(rng, repo_root):
    p = _random_promp(rng)
    d = promp_body(p)
    schema = json.load(open(os.path.join(repo_root, 'msg_schemas', 'primitive.schema.json')))
    doc = {'format_version': 1, 'kind': 'promp', 'joint_names': ['x', 'y'], 'n_dims': 2,
           'duration': 1.0, 'promp': json.loads(json.dumps(d))}
    jsonschema.validate(doc, schema)
    q = promp_from_dict(doc['promp'], n_dims=2)
    s = np.linspace(0, 1, 9)
    assert np.array_equal(q.mean(s), p.mean(s))
    assert np.array_equal(q.cov_w, p.cov_w)
    bad = dict(d, mean_w=d['mean_w'][:-1])
    with pytest.raises(PrimitiveFileError, match='mean_w'):
        promp_from_dict(bad)
    with pytest.raises(PrimitiveFileError, match='cov_w'):
        promp_from_dict({k: v for k, v in d.items() if k != 'cov_w'})


def test_the_compact_covariance_is_exact_and_checked_before_decoding(rng, repo_root):
    """``cov_w_base64`` (the adapter's messages) gives the same matrix bit for bit as
    ``cov_w``, validates against the schema, and a wrong size, bad characters, a non-finite
    entry, an asymmetric matrix or both forms at once are refused naming the field."""
    import base64
    from cdmp_ros.core.primitive_io import validate_primitive_dict
    p = _random_promp(rng)
    p.joint_names = ['a', 'b']
    doc = json.loads(json.dumps(primitive_to_dict(p)))
    compact = json.loads(json.dumps(dict(doc, promp=promp_body(p, compact=True))))
    assert 'cov_w' not in compact['promp']
    text = compact['promp']['cov_w_base64']
    n = p.cov_w.shape[0]
    assert len(text) == base64_length(n * n) == 4 * int(np.ceil(8 * n * n / 3))
    # the schema's own recipe decodes it
    C = np.frombuffer(base64.b64decode(text), '<f8').reshape(n, n)
    assert np.array_equal(C, p.cov_w)
    schema = json.load(open(os.path.join(repo_root, 'msg_schemas', 'primitive.schema.json')))
    jsonschema.validate(compact, schema)
    assert np.array_equal(primitive_from_dict(compact).cov_w, p.cov_w)
    assert np.array_equal(promp_from_dict(compact['promp'], n_dims=2).cov_w, p.cov_w)

    def refused(body_change, match):
        bad = json.loads(json.dumps(compact))
        body_change(bad['promp'])
        with pytest.raises(PrimitiveFileError, match=match):
            validate_primitive_dict(bad)

    def encode(M):
        return base64.b64encode(np.ascontiguousarray(M, '<f8').tobytes()).decode()
    refused(lambda b: b.update(cov_w_base64=text[:-4]),
            rf'primitive.promp.cov_w_base64: expected {len(text)} characters')
    refused(lambda b: b.update(cov_w_base64='*' + text[1:]), 'cov_w_base64: not valid base64')
    nan = p.cov_w.copy()
    nan[1, 2] = np.inf
    refused(lambda b: b.update(cov_w_base64=encode(nan)), r'cov_w_base64: entry \[1\]\[2\]')
    asym = p.cov_w.copy()
    asym[0, 1] += 1.0
    refused(lambda b: b.update(cov_w_base64=encode(asym)),
            r'cov_w_base64 entry \[0\]\[1\] and primitive.promp.cov_w_base64 entry \[1\]\[0\]')
    refused(lambda b: b.update(cov_w=doc['promp']['cov_w']),
            r"expected exactly one of the fields \['cov_w', 'cov_w_base64'\]")
    refused(lambda b: b.pop('cov_w_base64'), 'exactly one of the fields')


def test_primitive_file_round_trip_through_primitive_io(rng):
    p = _random_promp(rng)
    p.joint_names = ['a', 'b']
    p.duration = 2.5
    doc = json.loads(json.dumps(primitive_to_dict(p)))
    assert doc['kind'] == 'promp' and doc['n_dims'] == 2 and doc['duration'] == 2.5
    q = primitive_from_dict(doc)
    assert isinstance(q, ProMP) and q.joint_names == ['a', 'b'] and q.duration == 2.5
    assert np.array_equal(q.cov_w, p.cov_w) and np.array_equal(q.mean_w, p.mean_w)
    doc['promp']['cov_w'] = doc['promp']['cov_w'][:-1]
    with pytest.raises(PrimitiveFileError, match='cov_w'):
        primitive_from_dict(doc)


def test_validation_errors_name_the_variable():
    with pytest.raises(ValidationError, match='cov_w'):
        ProMP(2, RbfBasis.uniform(3), np.zeros(6), np.ones((5, 5)))
    with pytest.raises(ValidationError, match='width'):
        RbfBasis((0.0, 1.0), -1.0)
