"""A differentiable term computed on the side thread (warpbags.threads.beside_render): its value and gradients, and
gradients summed in the same order whatever the threads did before."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest
import torch

from warpbags.threads import beside_render

# Autograd walks ready nodes by a sequence number each thread counts for itself. The leaf takes three gradients,
# 1 and -1 from the calling thread's graph and 1e-8 from the side term: summed as (1 + -1) + 1e-8 or as
# (1e-8 + 1) + -1 they differ in float32. A side graph fed into the main one straight (what the trainer did) was
# walked after the main graph's nodes or before them depending on which thread had made more nodes (measured with
# this script: 1e-8 and 0). A fresh process lets the script push either thread's count past the other's cheaply.
ORDER_SCRIPT = textwrap.dedent("""
    import torch
    from warpbags.threads import beside_render, side_thread

    def gradient():
        x = torch.ones(3, requires_grad=True)
        side = beside_render(lambda leaf: (leaf * 1e-8).sum(), x)
        loss = (x * 1.0).sum() + (x * -1.0).sum()
        (loss + side()).backward()
        return x.grad.tolist()

    def nodes_made(count):  # the sequence number of the last of `count` new nodes on the calling thread
        leaf = torch.zeros(1, requires_grad=True)
        for _ in range(count):
            node = (leaf * 1.0).grad_fn
        return node._sequence_nr()

    nodes_made(side_thread().submit(nodes_made, 1).result() + 1000)  # the calling thread ahead
    main_ahead = gradient()
    side_thread().submit(nodes_made, nodes_made(1) + 1000).result()  # the side thread ahead
    side_ahead = gradient()
    print(main_ahead == side_ahead, main_ahead, side_ahead)
""")


def test_a_side_term_is_summed_into_the_gradients_in_the_same_order_whatever_the_threads_did_before():
    result = subprocess.run([sys.executable, "-c", ORDER_SCRIPT], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("True"), result.stdout


def test_a_side_term_has_the_value_and_gradients_of_the_term_computed_in_line():
    generator = torch.Generator().manual_seed(0)
    points = torch.randn(50, 3, dtype=torch.float64, generator=generator, requires_grad=True)
    weights = torch.rand(50, dtype=torch.float64, generator=generator, requires_grad=True)
    scale = torch.tensor(2.5, dtype=torch.float64)  # a tensor that needs no gradient passes through as it is

    def term(p, w, s):
        return (s * w[:, None] * p.sin()).sum() + (p.norm(dim=-1) * w).mean()

    expected = term(points, weights, scale)
    expected_grads = torch.autograd.grad(expected, (points, weights))
    joined = beside_render(term, points, weights, scale)()
    assert joined.grad_fn is not None and torch.equal(joined.detach(), expected.detach())
    for got, want in zip(torch.autograd.grad(3.0 * joined, (points, weights)), expected_grads):
        torch.testing.assert_close(got, 3.0 * want, rtol=1e-14, atol=0)
    with torch.no_grad():
        assert beside_render(term, points, weights, scale)().grad_fn is None


def test_a_side_term_refuses_what_it_cannot_differentiate():
    """Tensors inside a container lost their gradients silently; a gradient made to be differentiated again held the
    side term's part as a constant; a second backward raised an AttributeError."""
    x = torch.tensor([1.0, 2.0], dtype=torch.float64, requires_grad=True)
    with pytest.raises(TypeError, match="not inside containers"):
        beside_render(lambda point, others: (point * others[0]).sum(), x, [x * 2])
    term = beside_render(lambda point: (point ** 3).sum(), x)()
    with pytest.raises(RuntimeError, match="first derivatives only"):
        torch.autograd.grad(term + (x ** 2).sum(), x, create_graph=True)
    term = beside_render(lambda point: (point ** 3).sum(), x)()
    term.backward(retain_graph=True)
    with pytest.raises(RuntimeError, match="differentiated once"):
        term.backward()
