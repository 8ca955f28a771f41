"""dvsland.pytree: tree operations on stage states, counter-based draws, ObjectStage."""

from __future__ import annotations

from typing import NamedTuple, Optional

import pytest
import torch

from dvsland.pytree import (ObjectStage, ObjectState, check_state_like, hash_bits, hash_normal, hash_uniform,
                            packed_append, tree_clone, tree_equal, tree_leaves, tree_to, tree_where)


class Inner(NamedTuple):
    count: torch.Tensor


class S(NamedTuple):
    x: torch.Tensor
    inner: Inner
    maybe: Optional[torch.Tensor]


def _s(B=3):
    return S(torch.arange(B * 2, dtype=torch.float64).view(B, 2), Inner(torch.zeros(B, dtype=torch.int64)), None)


def test_clone_where_equal_leaves():
    a = _s()
    b = tree_clone(a)
    assert tree_equal(a, b) and b.x.data_ptr() != a.x.data_ptr()
    b = b._replace(x=b.x + 10, inner=Inner(b.inner.count + 1))
    m = torch.tensor([True, False, True])
    w = tree_where(m, b, a)
    assert torch.equal(w.x[1], a.x[1]) and torch.equal(w.x[0], b.x[0]) and w.inner.count.tolist() == [1, 0, 1]
    assert w.maybe is None and set(tree_leaves(a)) == {"x", "inner.count"}
    assert tree_equal(tree_to(a, "cpu"), a)
    nan = a._replace(x=torch.full((3, 2), float("nan"), dtype=torch.float64))
    assert tree_equal(nan, tree_clone(nan)) and not tree_equal(nan, a)


def test_where_refuses_a_shared_leaf_that_differs():
    a, b = (_s()._replace(maybe=torch.zeros(7)), _s()._replace(maybe=torch.ones(7)))
    with pytest.raises(ValueError, match="not batch first"):
        tree_where(torch.tensor([True, False, False]), b, a)
    assert torch.equal(tree_where(torch.ones(3, dtype=torch.bool), b, a).maybe, b.maybe)  # every descent: new


def test_check_state_like_names_the_field():
    ref = _s()
    check_state_like("demo", _s(), ref)
    with pytest.raises(ValueError, match=r"demo: state field 'inner.count' must have dtype torch.int64, got torch.int32"):
        check_state_like("demo", ref._replace(inner=Inner(ref.inner.count.int())), ref)
    with pytest.raises(ValueError, match=r"demo: state field 'x' must have shape \(3, 2\), got \(4, 2\)"):
        check_state_like("demo", _s(4)._replace(inner=ref.inner), ref)
    with pytest.raises(ValueError, match="demo: state must be a S"):
        check_state_like("demo", (1, 2), ref)


def test_hash_draws_are_keyed_and_uniform():
    k = torch.arange(200_000)
    u = hash_uniform(7, k, 3)
    assert torch.equal(u, hash_uniform(7, k, 3)) and not torch.equal(u, hash_uniform(8, k, 3))
    assert 0 < float(u.min()) and float(u.max()) < 1 and abs(float(u.mean()) - 0.5) < 0.005
    assert abs(float(u.var()) * 12 - 1) < 0.02
    # a descent's draws depend on its keys only: the same keys inside a larger batch give the same bits
    assert torch.equal(hash_bits(torch.tensor([5, 9]), 2)[1], hash_bits(torch.tensor([9]), 2)[0])
    n = hash_normal(1, k)
    assert abs(float(n.mean())) < 0.01 and abs(float(n.std()) - 1) < 0.01
    big = hash_bits(torch.tensor([2 ** 62 + 5]), 1)  # 64-bit keys fold both halves
    assert 0 <= int(big) < 2 ** 32 and int(big) != int(hash_bits(torch.tensor([5]), 1))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_hash_draws_same_on_cuda():
    k = torch.arange(10_000)
    assert torch.equal(hash_bits(3, k, 4), hash_bits(3, k.cuda(), 4).cpu())


class _Counter:
    """An object-API plug-in: hidden state in attributes."""

    def __init__(self):
        self.n = torch.zeros(2)

    def reset(self, mask=None):
        self.n = torch.where(torch.ones(2, dtype=torch.bool) if mask is None else mask, torch.zeros(2), self.n)

    def update(self, x):
        self.n = self.n + x
        return self.n.clone()


def test_object_stage_makes_hidden_state_data():
    obj = _Counter()
    st = ObjectStage(obj, call=lambda o, x: o.update(x), reset=lambda o, m: o.reset(m))
    s0 = st.init_state()
    s1, out1 = st.step_state(s0, torch.ones(2))
    s2, out2 = st.step_state(s1, torch.ones(2))
    again, out1b = st.step_state(s0, torch.ones(2))  # stepping from an older state restores it
    assert isinstance(s0, ObjectState) and out2.tolist() == [2.0, 2.0] and torch.equal(out1, out1b)
    r = st.reset_where(s2, torch.tensor([True, False]))
    assert r.attrs["n"].tolist() == [0.0, 2.0] and s2.attrs["n"].tolist() == [2.0, 2.0]


# ------------------------------------------------------------------ packed_append
def test_packed_append_is_cat_and_leaves_every_earlier_field_unchanged():
    g = torch.Generator().manual_seed(0)
    field = torch.zeros(0, dtype=torch.int64)
    history = []
    for k in range(30):
        new = torch.randint(0, 1000, (int(torch.randint(0, 50, (1,), generator=g)),), generator=g)
        want = torch.cat([field, new])
        field = packed_append(field, new)
        assert torch.equal(field, want) and field.dtype == want.dtype
        if k % 7 == 3:  # cut from the front, as a pruned ring
            field = field[5:]
        history.append((field, field.clone()))
    for view, copy in history:
        assert torch.equal(view, copy)  # no append wrote into an earlier field


def test_packed_append_reuses_its_buffer_and_copies_a_branch():
    a = packed_append(torch.arange(4.0), torch.arange(3.0))
    b = packed_append(a, torch.tensor([9.0]))  # the newest view: written after it, no copy
    assert b.untyped_storage().data_ptr() == a.untyped_storage().data_ptr()
    c = packed_append(a, torch.tensor([7.0, 8.0]))  # `a` stepped again: a new buffer, `b` unchanged
    assert c.untyped_storage().data_ptr() != a.untyped_storage().data_ptr()
    assert torch.equal(b, torch.tensor([0.0, 1, 2, 3, 0, 1, 2, 9]))
    assert torch.equal(c, torch.tensor([0.0, 1, 2, 3, 0, 1, 2, 7, 8]))


def test_packed_append_falls_back_to_cat():
    x = torch.arange(3.0, requires_grad=True)
    out = packed_append(x, torch.ones(2))
    assert out.requires_grad and torch.equal(out.detach(), torch.tensor([0.0, 1, 2, 1, 1]))
    mixed = packed_append(torch.arange(3), torch.ones(2))  # int64 then float32: cat's promotion
    assert mixed.dtype == torch.float32 and torch.equal(mixed, torch.tensor([0.0, 1, 2, 1, 1]))
    two_d = packed_append(torch.zeros(2, 3), torch.ones(1, 3))
    assert two_d.shape == (3, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_packed_append_on_cuda_reuses_its_buffer():
    a = packed_append(torch.arange(5, device="cuda"), torch.arange(3, device="cuda"))
    b = packed_append(a, torch.tensor([9], device="cuda"))
    assert b.device.type == "cuda" and b.untyped_storage().data_ptr() == a.untyped_storage().data_ptr()
    assert b.cpu().tolist() == [0, 1, 2, 3, 4, 0, 1, 2, 9] and a.cpu().tolist() == [0, 1, 2, 3, 4, 0, 1, 2]
