"""Counter-based seeding: every random draw in the data layer is a pure function of its key."""

from __future__ import annotations

import hashlib

import torch


def derive_seed(*key: object) -> int:
    """A 63-bit seed from any tuple of printable parts (seed, split name, rank, index, ...)."""
    digest = hashlib.sha256(repr(key).encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def generator_for(*key: object) -> torch.Generator:
    """A CPU generator seeded by :func:`derive_seed`."""
    return torch.Generator().manual_seed(derive_seed(*key))
