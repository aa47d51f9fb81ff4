"""Process-wide choices between two forms of a CPU kernel: set from per-machine measurements, overridable in a block.

`carp.policy.blocks` (block-causal attention) and `carp.tokenizer.autoencoder` (single-group convolutions) each keep
one; the benchmarks override them to time both forms on the same machine.
"""

import contextlib
from collections.abc import Iterator


class KernelChoice:
    """Whether a CPU kernel's alternative form is on (`enabled`); `overridden` switches it inside a `with` block."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled

    @contextlib.contextmanager
    def overridden(self, enabled: bool | None) -> Iterator[None]:
        """Set the choice to `enabled` inside the block (None leaves it as it is) and restore it on exit."""
        previous = self.enabled
        self.enabled = previous if enabled is None else enabled
        try:
            yield
        finally:
            self.enabled = previous
