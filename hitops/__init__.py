"""HITOPS: High-frequency Inter-band Transfer of Phase Solutions.

Frequency phase transfer (FPT) for millimetre VLBI at arbitrary frequency
ratios: classical FPT, FPT with unwrapping and phase-wrap counting (PWC),
a dual-band simulator and coherence diagnostics.
"""

__version__ = "0.1.0"
