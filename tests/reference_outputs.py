"""Comparing our model outputs with reference outputs stored in a file made on another machine.

Two computations on one machine are compared bit for bit. A stored reference was computed by the same
float32 operations, but possibly with other kernels: the CPU's vector width (AVX2's 8 lanes, AVX-512's
16), oneDNN / MKL blocking and the thread count decide the order in which every dot product, softmax
sum and normalisation mean is accumulated. Reordering a float32 sum of ``n`` terms changes it by at
most ``2 * n * u * sum(|terms|)`` (``u = 2**-24``, the unit roundoff), so the difference scales with
the magnitudes that enter the reduction, not with the result: an output near zero made of terms of
size one carries errors of size ``u``. Layer after layer these rounding differences are carried
forward and amplified by the network's conditioning, never created from nothing.

The bound used here is therefore relative to a tensor's scale (its largest magnitude, which stands in
for the size of the terms that produced it): ``|ours - reference| <= REFERENCE_ULPS * eps * scale``
elementwise, ``eps = 2**-23`` being the float32 spacing at 1. ``REFERENCE_ULPS`` is 256: the largest
difference measured over every stored output of every model fixture (VGGT, SALAD, Depth Anything 3,
π³ / Pi3X), with three kernel paths on one AVX-512/AMX CPU (its own, and AVX2 and the plain path forced
with ``ATEN_CPU_CAPABILITY=avx2|default``, ``ONEDNN_MAX_CPU_ISA=AVX2|SSE41`` and
``MKL_ENABLE_INSTRUCTIONS=AVX2|SSE4_2``), was ``MEASURED_ULPS`` spacings at the tensor's scale; 256
leaves a margin of 10x for other CPUs and thread counts. It is still far below what a wrong
computation gives (``tests/test_reference_outputs.py`` drops one bias of a tiny VGGT and checks that
the outputs move by more than 10x the bound).

Cameras fitted to predicted rays (Depth Anything 3's ray head) come from a least-squares fit inside
RANSAC, whose conditioning amplifies the rays' differences: rays one spacing apart gave cameras up to
``MEASURED_FIT_ULPS`` spacings apart. Those outputs take ``FIT_ULPS``, the same 8x margin over what was
measured (2e-3 of the tensor's scale).

Integer and boolean outputs are discrete: they must be equal.
"""

from __future__ import annotations

import torch

FLOAT32_EPS = 2.0**-23
"""Spacing of float32 numbers at 1.0."""

REFERENCE_ULPS = 256
"""Allowed difference to a stored reference, in float32 spacings at the tensor's largest magnitude."""

MEASURED_ULPS = 25
"""Largest difference measured over every fixture and kernel path (module docstring), same unit."""

FIT_ULPS = 2**14
"""Allowed difference for cameras fitted to predicted rays (module docstring), same unit."""

MEASURED_FIT_ULPS = 1938
"""Largest difference of ray-fitted cameras measured over the kernel paths, same unit."""


def scale_of(reference: torch.Tensor) -> float:
    """The tensor's largest finite magnitude (1.0 for an empty or all-zero tensor)."""
    reference = reference.detach()
    finite = reference[torch.isfinite(reference)] if reference.is_floating_point() else reference
    if finite.numel() == 0:
        return 1.0
    largest = float(finite.double().abs().max())
    return largest if largest > 0 else 1.0


def spacings_apart(ours: torch.Tensor, reference: torch.Tensor) -> float:
    """Largest elementwise difference in float32 spacings at the reference's scale (0 when equal)."""
    difference = (ours.detach().double() - reference.detach().double()).abs()
    both_nan = torch.isnan(ours) & torch.isnan(reference)
    same_inf = torch.isinf(reference) & (ours == reference)
    difference = torch.where(both_nan | same_inf, torch.zeros_like(difference), difference)
    if difference.numel() == 0:
        return 0.0
    return float(difference.max()) / (FLOAT32_EPS * scale_of(reference))


def assert_matches_reference(ours: torch.Tensor, reference: torch.Tensor, name: str,
                             ulps: float = REFERENCE_ULPS) -> None:
    """Assert that ``ours`` equals a stored reference output up to float32 reordering (module doc).

    Args:
        ours: our output, any shape.
        reference: the stored output, same shape and dtype.
        name: what is compared, for the failure message.
        ulps: the bound in float32 spacings at the reference's scale.

    Raises:
        AssertionError: shapes or dtypes differ, a discrete output differs, or a float output is
            farther than the bound (the message gives the distance in spacings).
    """
    assert ours.shape == reference.shape, f"{name}: shape {tuple(ours.shape)} != {tuple(reference.shape)}"
    assert ours.dtype == reference.dtype, f"{name}: dtype {ours.dtype} != {reference.dtype}"
    if not reference.is_floating_point():
        assert torch.equal(ours, reference), f"{name}: discrete outputs differ"
        return
    assert torch.equal(torch.isnan(ours), torch.isnan(reference)), f"{name}: NaN in different places"
    apart = spacings_apart(ours, reference)
    assert apart <= ulps, (f"{name}: {apart:.3g} float32 spacings from the reference at its scale "
                           f"{scale_of(reference):.3g} (bound {ulps})")

