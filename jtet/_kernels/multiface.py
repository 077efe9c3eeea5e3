"""The tree dynamic program of optimal multi-face removal: a JAX kernel for ONE tree.

Shewchuk, Section 3 (Figure 11, REMOVEMULTIFACE / TESTNEIGHBOR). The faces sandwiched
between two vertices ``a`` and ``b`` that the search reached form a tree ``G'`` rooted at the
face crossed by segment ``ab``. Node ``i`` is the face ``(x0, x1, x2)``, counterclockwise
seen from ``a``; its slot ``s`` is the edge ``x_s -> x_{s+1 mod 3}``. For a non-root node,
slot 2 is the edge it shares with its parent (the parent traverses it the other way), so
only slots 0 and 1 can hold children; the root uses all three slots.

Removing a set ``S`` of faces (a subtree containing the root) deletes the ``2|S|`` tets
``(face, a)`` and ``(face, b)`` and creates one tet ``(a, b, x_{s+1}, x_s)`` (positively
oriented in jtet's VTK convention) for every slot edge on the boundary of ``S``.

The kernel is TESTNEIGHBOR run bottom-up: nodes are in BFS order (a parent precedes its
children), so one reverse sweep over the static node capacity visits every child before its
parent. For node ``g`` with parent edge tet quality ``q_uw`` it computes ``q_old`` (worst tet
removed in g's subtree if g goes) and ``q_new`` (worst tet created) and decides to remove
g (given that its parent goes) iff ``q_new > q_old or q_new > q_uw`` (Figure 11, line 27).
A forward sweep then marks ``G''``: the nodes removed together with all their ancestors.

What this optimizes (verified by brute force in tests/test_multiface.py): among the
subtrees ``S`` of ``G'`` containing the root, the chosen ``G''`` maximizes the worst quality
of the tets of the region after the removal, ``min(kept tets of G', created tets)``; and
``q_new > q_old`` holds at the root iff some subtree ``S`` has ``q_new(S) > q_old(S)``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._quality import get_measure

__all__ = ["slot_quality", "solve_trees", "tree_dp", "tree_kernel"]


def slot_quality(
    a: tuple, b: tuple, vx: Array, vy: Array, vz: Array, *, measure: str
) -> Float[Array, "N 3"]:
    """Quality of the tet ``(a, b, x_{s+1}, x_s)`` of every slot of one tree: (N, 3).

    ``a``, ``b``: SoA scalars ``(x, y, z)``; ``vx, vy, vz``: (N, 3) node corners. Only the
    ``2N + 1`` slots that can bound a removal are evaluated (slot 2 of a non-root node is
    its parent's edge; it gets +inf), in ONE elementwise SoA call of the measure.
    """
    q = get_measure(measure)
    n = vx.shape[0]
    # slots 0 and 1 of every node, then slot 2 of the root: corners x_{s+1} and x_s
    nxt = tuple(jnp.concatenate([v[:, 1:].reshape(-1), v[:1, 0]]) for v in (vx, vy, vz))
    cur = tuple(jnp.concatenate([v[:, :2].reshape(-1), v[:1, 2]]) for v in (vx, vy, vz))
    pa = tuple(jnp.broadcast_to(c, (2 * n + 1,)) for c in a)
    pb = tuple(jnp.broadcast_to(c, (2 * n + 1,)) for c in b)
    qs = q(pa, pb, nxt, cur)
    inf = jnp.full((n, 1), jnp.inf, qs.dtype).at[0, 0].set(qs[-1])
    return jnp.concatenate([qs[:-1].reshape(n, 2), inf], axis=1)


def tree_kernel(
    ax, ay, az, bx, by, bz,
    vx: Float[Array, "N 3"],
    vy: Float[Array, "N 3"],
    vz: Float[Array, "N 3"],
    parent: Int[Array, " N"],
    pslot: Int[Array, " N"],
    child: Int[Array, "N 3"],
    q_tet: Float[Array, " N"],
    valid: Bool[Array, " N"],
    n_live=None,
    *,
    measure: str,
) -> tuple[Float[Array, ""], Float[Array, ""], Bool[Array, " N"]]:  # fmt: skip
    """Optimal multi-face removal over ONE padded tree (vmap it over a batch).

    Args:
        ax .. bz: scalar coordinates of the apexes ``a`` and ``b``.
        vx, vy, vz: (N, 3) corners ``x0, x1, x2`` of every node (counterclockwise seen
            from ``a``; slot 2 is the parent edge of a non-root node).
        parent: (N,) parent node (any value for the root, node 0, and for padding).
        pslot: (N,) the parent's slot holding this node.
        child: (N, 3) child node in each slot, -1 if none (and -1 in slot 2 of non-roots).
        q_tet: (N,) worst quality of the two tets ``(face, a)``, ``(face, b)``.
        valid: (N,) False for padding nodes (node 0 must be valid for a real tree).
        n_live: nodes from this index on are padding (default N); a traced scalar shared
            by the batch (not vmapped), so small trees in a large capacity cost few steps.

    Returns:
        ``(q_old, q_new, chosen)``: the worst tet the removal of ``G''`` deletes and the
        worst it creates (the removal is an improvement iff ``q_new > q_old``), and the
        (N,) mask of ``G''`` (root always included).
    """
    qs = slot_quality((ax, ay, az), (bx, by, bz), vx, vy, vz, measure=measure)
    return tree_dp(qs, q_tet, parent, pslot, child, valid, n_live)


def tree_dp(
    qs: Float[Array, "N 3"],
    q_tet: Float[Array, " N"],
    parent: Int[Array, " N"],
    pslot: Int[Array, " N"],
    child: Int[Array, "N 3"],
    valid: Bool[Array, " N"],
    n_live=None,
) -> tuple[Float[Array, ""], Float[Array, ""], Bool[Array, " N"]]:
    """TESTNEIGHBOR bottom-up and the marking of ``G''`` for ONE tree, from qualities.

    ``qs`` (N, 3): quality of the tet each slot edge would create; other arguments as in
    ``tree_kernel``. Two ``fori_loop`` sweeps over the first ``n_live`` nodes (one gather
    per step): the compile time does not grow with N (unrolling over N did, steeply).
    """
    n = qs.shape[0]
    n_live = n if n_live is None else n_live
    inf = jnp.asarray(jnp.inf, qs.dtype)
    # q_uw of every node: the tet its parent creates on the shared edge if it stays
    q_par = qs[jnp.clip(parent, 0, n - 1), jnp.clip(pslot, 0, 2)]
    slot_live = jnp.asarray([True, True, False])

    def up(step, carry):
        ret_o, ret_n, rem, root = carry
        i = n_live - 1 - step
        c = child[i]
        has = c >= 0
        cc = jnp.clip(c, 0, n - 1)
        o = jnp.where(has, ret_o[cc], inf)
        nn = jnp.where(has, ret_n[cc], qs[i])
        live = slot_live | (i == 0)  # slot 2 is the parent edge, except at the root
        o = jnp.where(live, o, inf)
        nn = jnp.where(live, nn, inf)
        qo = jnp.minimum(q_tet[i], jnp.min(o))
        qn = jnp.min(nn)
        remove = (qn > qo) | (qn > q_par[i])  # Figure 11, line 27
        ret_o = ret_o.at[i].set(jnp.where(remove, qo, inf))
        ret_n = ret_n.at[i].set(jnp.where(remove, qn, q_par[i]))
        rem = rem.at[i].set(remove)
        root = jnp.where(i == 0, jnp.stack([qo, qn]), root)
        return ret_o, ret_n, rem, root

    init = (jnp.full(n, inf), jnp.full(n, inf), jnp.zeros(n, bool), jnp.zeros(2, qs.dtype))
    _, _, rem, root = jax.lax.fori_loop(0, n_live, up, init)

    def down(i, chosen):
        take = rem[i] & chosen[jnp.clip(parent[i], 0, n - 1)] & valid[i]
        return chosen.at[i].set(take)

    chosen0 = jnp.zeros(n, bool).at[0].set(valid[0])
    chosen = jax.lax.fori_loop(1, n_live, down, chosen0)
    return root[0], root[1], chosen


@functools.partial(jax.jit, static_argnames=("measure",))
def solve_trees(
    ax, ay, az, bx, by, bz, vx, vy, vz, parent, pslot, child, q_tet, valid, n_live, *, measure
):
    """``tree_kernel`` vmapped over a batch of B padded trees (leading axis of every array).

    ``n_live``: scalar, the largest tree of the batch (nodes at and past it are padding in
    every tree). One compiled kernel per (batch capacity, tree capacity N, measure):
    callers pad B to ``_config.bucket_capacity`` and N to a few fixed tree capacities.
    Returns ``(q_old (B,), q_new (B,), chosen (B, N))``.
    """
    kern = functools.partial(tree_kernel, measure=measure)
    axes = (0,) * 14 + (None,)
    return jax.vmap(kern, in_axes=axes)(
        ax, ay, az, bx, by, bz, vx, vy, vz, parent, pslot, child, q_tet, valid, n_live
    )
