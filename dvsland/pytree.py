"""Stage state as data: the stage contract of the loop and the tree operations on states.

Every stateful stage of the loop (the emulator, the estimator, the filter, the law) is three
things, as norse's ``LIFParameters`` / ``LIFState`` / ``lif_step``:

- ``params``: frozen settings (the stage's config section itself, or a frozen dataclass built
  from it once); never written in flight;
- a ``State``: a NamedTuple whose leaves are tensors (batch first: dim 0 is the descent), None,
  or plain Python values that never differ between descents. Random keys are data too (a seed per
  descent and a step counter: counter-based draws, :func:`hash_uniform`);
- a pure step: ``step_state(state, *inputs) -> (state, outputs)`` that neither changes ``state``
  nor keeps anything elsewhere, so the same state stepped twice gives the same outputs.

Each stage object offers that contract as methods (``init_state(...)``, ``step_state(state, ...)``,
``reset_where(state, mask, ...)``) over module-level pure functions, and keeps its old object API
(``update``, ``reset``, ``__call__``) as a thin wrapper that holds one state. The loop
(:mod:`dvsland.sim`) only uses the contract; a third-party object that only has the object API is
run through :class:`ObjectStage`, which makes its state data by copying the object's attributes.

Tree operations (leaves are tensors; NamedTuples, tuples, lists and dicts are walked; None and
other values are kept as they are): :func:`tree_map`, :func:`tree_clone`, :func:`tree_to`,
:func:`tree_where` (per-descent selection, the heart of a per-descent reset), :func:`tree_equal`,
:func:`check_state_like`; :func:`packed_append` grows a packed (variable-length) field without
copying it whole.
"""

from __future__ import annotations

import copy
from typing import Any, Callable, Dict, NamedTuple, Optional

import torch

Tree = Any


# ------------------------------------------------------------------ tree operations
def _is_namedtuple(x: Any) -> bool:
    return isinstance(x, tuple) and hasattr(x, "_fields")


def tree_map(fn: Callable[..., Any], tree: Tree, *rest: Tree) -> Tree:
    """Apply ``fn(leaf, *other_leaves)`` to every tensor leaf of ``tree`` (and the matching leaves
    of ``rest``, trees of the same structure); other leaves are kept from ``tree``."""
    if isinstance(tree, torch.Tensor):
        return fn(tree, *rest)
    if _is_namedtuple(tree):
        return type(tree)(*(tree_map(fn, a, *(r[i] for r in rest)) for i, a in enumerate(tree)))
    if isinstance(tree, (tuple, list)):
        return type(tree)(tree_map(fn, a, *(r[i] for r in rest)) for i, a in enumerate(tree))
    if isinstance(tree, dict):
        return {k: tree_map(fn, v, *(r[k] for r in rest)) for k, v in tree.items()}
    return tree


def tree_leaves(tree: Tree, prefix: str = "") -> Dict[str, torch.Tensor]:
    """The tensor leaves of ``tree`` by dotted path (``"lref"``, ``"denoise.last_t_us"``)."""
    out: Dict[str, torch.Tensor] = {}
    if isinstance(tree, torch.Tensor):
        out[prefix or "."] = tree
    elif _is_namedtuple(tree):
        for k, v in zip(tree._fields, tree):
            out.update(tree_leaves(v, f"{prefix}.{k}" if prefix else k))
    elif isinstance(tree, (tuple, list)):
        for i, v in enumerate(tree):
            out.update(tree_leaves(v, f"{prefix}[{i}]"))
    elif isinstance(tree, dict):
        for k, v in tree.items():
            out.update(tree_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def tree_clone(tree: Tree) -> Tree:
    """An independent copy: every tensor leaf cloned (other leaves shared: they are immutable)."""
    return tree_map(lambda t: t.clone(), tree)


def tree_to(tree: Tree, device: Any) -> Tree:
    """Every tensor leaf moved to ``device``."""
    dev = torch.device(device)
    return tree_map(lambda t: t.to(dev), tree)


def tree_where(mask: torch.Tensor, new: Tree, old: Tree) -> Tree:
    """Per-descent selection: leaf ``new`` where ``mask`` (B,) bool is True, else ``old``.

    Tensor leaves are batch first ((B, ...), broadcast over the trailing dims). A leaf whose first
    dim is not B (a shared table) is taken from ``new`` when every descent is selected, else it
    must be the same in both (else ValueError naming its path).
    """
    B = int(mask.shape[0])
    every = None

    def pick(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        nonlocal every
        if a.dim() >= 1 and a.shape[0] == B and b.shape == a.shape:
            m = mask.to(a.device).view((B,) + (1,) * (a.dim() - 1))
            return torch.where(m, a, b)
        if every is None:
            every = bool(mask.all())
        if every:
            return a
        if a.shape == b.shape and torch.equal(a, b):
            return b
        raise ValueError(f"tree_where: a leaf of shape {tuple(a.shape)} is not batch first (B={B}) and differs "
                         "between the states: it cannot be selected per descent")
    return tree_map(pick, new, old)


def tree_equal(a: Tree, b: Tree) -> bool:
    """True when both trees have the same structure and bit-identical leaves (NaN equals NaN)."""
    la, lb = tree_leaves(a), tree_leaves(b)
    if la.keys() != lb.keys():
        return False
    for k in la:
        x, y = la[k], lb[k]
        if x.shape != y.shape or x.dtype != y.dtype:
            return False
        if x.is_floating_point():
            if not torch.equal(torch.isnan(x), torch.isnan(y)) or not torch.equal(x.nan_to_num(0.0), y.nan_to_num(0.0)):
                return False
        elif not torch.equal(x, y):
            return False
    return True


def check_state_like(stage: str, state: Tree, reference: Tree) -> None:
    """Check that ``state`` has the structure, shapes, dtypes and devices of ``reference`` (a state
    the stage itself made for the same params and batch).

    Raises:
        ValueError: one message naming the stage, the field, what was expected and what came.
    """
    if type(state) is not type(reference):
        raise ValueError(f"{stage}: state must be a {type(reference).__name__}, got {type(state).__name__}")
    got, want = tree_leaves(state), tree_leaves(reference)
    for k, w in want.items():
        g = got.get(k)
        if g is None:
            raise ValueError(f"{stage}: state field {k!r} must be a tensor of shape {tuple(w.shape)}, got None")
        for what, gv, wv in (("shape", tuple(g.shape), tuple(w.shape)), ("dtype", g.dtype, w.dtype),
                             ("device", g.device, w.device)):
            if what == "shape" and k.endswith("_packed"):  # packed (variable-length) leaves: rank only
                gv, wv = len(gv), len(wv)
            if gv != wv:
                raise ValueError(f"{stage}: state field {k!r} must have {what} {wv}, got {gv}")



# ------------------------------------------------------------------ packed fields
#: the attribute of a packed field's buffer that holds how far it is written (elements)
_PACKED_END = "_dvsland_packed_end"
#: a packed field's new buffer holds this many times what it needs (amortised appends)
PACKED_GROWTH = 2


def packed_append(old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
    """``torch.cat([old, new])`` for a packed (variable-length, 1-D) state field, pure, without
    copying ``old`` where it can.

    A packed field grows by a step's entries and is cut from the front (a ring of stored steps):
    copying it whole on every append costs its size per step. The result is a view of a buffer
    with room to grow (:data:`PACKED_GROWTH` times what it holds when made). An append to the
    newest view of a buffer writes ``new`` after it, past the end of every view made before, so
    no earlier state changes; an append to any other view (a state stepped twice, a reset one, a
    field from elsewhere) copies into a new buffer. The values, dtype and device are
    ``torch.cat``'s; tensors that need gradients, or of different dtypes or devices, take
    ``torch.cat`` itself.

    Args:
        old: (N,) the field. new: (M,) what comes after it.

    Returns:
        (N + M,) tensor.
    """
    if (old.dim() != 1 or new.dim() != 1 or old.dtype != new.dtype or old.device != new.device
            or old.requires_grad or new.requires_grad):
        return torch.cat([old, new])
    n_old, n_new = old.shape[0], new.shape[0]
    base = old._base
    if base is not None and base.dim() == 1 and old.stride(0) == 1 and base.stride(0) == 1:
        off = old.storage_offset() - base.storage_offset()
        end = off + n_old
        if getattr(base, _PACKED_END, None) == end and end + n_new <= base.shape[0]:
            base[end:end + n_new].copy_(new)
            setattr(base, _PACKED_END, end + n_new)
            return base[off:end + n_new]
    n = n_old + n_new
    buf = torch.empty(max(PACKED_GROWTH * n, 256), dtype=old.dtype, device=old.device)
    buf[:n_old].copy_(old)
    buf[n_old:n].copy_(new)
    setattr(buf, _PACKED_END, n)
    return buf[:n]

# ------------------------------------------------------------------ counter-based random numbers
_M1, _M2 = 0x7FEB352D, 0x846CA68B
_MASK32 = 0xFFFFFFFF


def _mix32(x):
    """A 32-bit integer finaliser (lowbias32) on int64 tensors holding values in [0, 2^32), or on a
    Python int in that range (the same bits); a tensor input is not written (one temporary is)."""
    if isinstance(x, int):
        x ^= x >> 16
        x = (x * _M1) & _MASK32
        x ^= x >> 15
        x = (x * _M2) & _MASK32
        return x ^ (x >> 16)
    x = x ^ (x >> 16)
    x.mul_(_M1).bitwise_and_(_MASK32)
    x.bitwise_xor_(x >> 15)
    x.mul_(_M2).bitwise_and_(_MASK32)
    return x.bitwise_xor_(x >> 16)


def _fold(h, part):
    """The hash ``h`` (None at the start) with one more 32-bit ``part`` folded in; ints stay ints."""
    return _mix32(part ^ 0x9E3779B9) if h is None else _mix32(h ^ _mix32(part + 0x632BE5AB))


def hash_bits(*keys: torch.Tensor) -> torch.Tensor:
    """32 random bits per element (int64 in [0, 2^32)) from integer keys, broadcast together.

    The same keys give the same bits on every device and batch size: the draws of a descent are a
    function of its keys only (seed, step, pixel, stream tag), never of its batch-mates. Keys are
    int64 tensors or Python ints (an int key is hashed on the host: no tensor operation, nothing
    launched on a GPU); each is folded in 32-bit halves.
    """
    return _as_bits(_fold_keys(None, keys))


def _fold_keys(h, keys):
    """``h`` with ``keys`` folded in, half by half (:func:`hash_bits` without the final tensor)."""
    for k in keys:
        if not isinstance(k, int):
            k = torch.as_tensor(k, dtype=torch.int64)
        for part in (k & _MASK32, (k >> 32) & _MASK32):
            h = _fold(h, part)
    return h


def _as_bits(h) -> torch.Tensor:
    return torch.as_tensor(h, dtype=torch.int64) if isinstance(h, int) else h


def _uniform(bits: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """32 hashed bits (int64 in [0, 2^32)) as a uniform draw in (0, 1) of ``dtype``."""
    return (bits.to(dtype) + 0.5) * (1.0 / 4294967296.0)


def hash_uniform(*keys: torch.Tensor, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Uniform draws in (0, 1) from integer keys (see :func:`hash_bits`), 32 bits of resolution."""
    return _uniform(hash_bits(*keys), dtype)


def hash_normal(*keys: torch.Tensor, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Standard normal draws from integer keys (Box-Muller over two hashed uniforms)."""
    h = _fold_keys(None, keys)  # the keys' hash once, then the two draws' own tags
    u1, u2 = (_uniform(_as_bits(_fold_keys(h, (i,))), dtype) for i in (1, 2))
    return torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * torch.pi * u2)


# ------------------------------------------------------------------ object plug-ins as stages
class ObjectState(NamedTuple):
    """The state of an object stage (:class:`ObjectStage`): a copy of the object's attributes."""

    attrs: Dict[str, Any]


class ObjectStage:
    """A stage with only the object API (``update``/``reset``/``__call__`` on hidden attributes) run
    under the stage contract: its state is a deep copy of its attributes (torch modules, whose
    weights do not change in flight, are shared, not copied).

    Args:
        obj: the object.
        call: ``call(obj, *inputs) -> outputs``, the object's step.
        reset: ``reset(obj, mask, *args)``, the object's restart of the masked descents (mask None =
            all); ``args`` are what ``reset_where`` is given after the mask.
        init: ``init(obj, *args)``, the object's start (default ``reset(obj, None)``).

    Cost: one deep copy of the object's attributes per step (the price of a state that can be kept,
    cloned and resumed); the object is not restored when stepped from the state it produced last.
    """

    def __init__(self, obj: Any, call: Callable[..., Any], reset: Callable[..., None],
                 init: Optional[Callable[..., None]] = None):
        self.obj, self._call, self._reset, self._init = obj, call, reset, init
        self._held: Optional[ObjectState] = None

    def _memo(self) -> dict:
        memo: dict = {id(self.obj): self.obj}
        for v in vars(self.obj).values():
            if isinstance(v, torch.nn.Module):
                memo[id(v)] = v
        return memo

    def _snapshot(self) -> ObjectState:
        st = ObjectState(copy.deepcopy(dict(vars(self.obj)), self._memo()))
        self._held = st
        return st

    def _adopt(self, state: ObjectState) -> None:
        if state is self._held:
            return
        if not isinstance(state, ObjectState):
            raise ValueError(f"{type(self.obj).__name__}: state must be an ObjectState, got {type(state).__name__}")
        fresh = copy.deepcopy(state.attrs, self._memo())
        vars(self.obj).clear()
        vars(self.obj).update(fresh)
        self._held = state

    def init_state(self, *args) -> ObjectState:
        """The object's state after its start (``init(obj, *args)`` or ``reset(obj, None)``)."""
        if self._init is not None:
            self._init(self.obj, *args)
        else:
            self._reset(self.obj, None, *args)
        return self._snapshot()

    def step_state(self, state: ObjectState, *inputs, **kw):
        """(the object's state after the call, the call's outputs); ``state`` is unchanged."""
        self._adopt(state)
        out = self._call(self.obj, *inputs, **kw)
        return self._snapshot(), out

    def reset_where(self, state: ObjectState, mask: torch.Tensor, *args) -> ObjectState:
        """The state with the masked descents restarted (the object's ``reset(mask, *args)``)."""
        self._adopt(state)
        self._reset(self.obj, mask, *args)
        return self._snapshot()


def has_stage_contract(obj: Any) -> bool:
    """True when ``obj`` offers the stage contract (``init_state``, ``step_state``, ``reset_where``)."""
    return all(callable(getattr(obj, m, None)) for m in ("init_state", "step_state", "reset_where"))


__all__ = ["tree_map", "tree_leaves", "tree_clone", "tree_to", "tree_where", "tree_equal", "check_state_like",
           "packed_append", "hash_bits", "hash_uniform", "hash_normal", "ObjectState", "ObjectStage",
           "has_stage_contract"]
