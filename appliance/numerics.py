"""Settings shared by the compiled (numba) kernels."""

#: Fast-math without the "no NaN, no inf" assumptions: the kernels test for NaN and use inf.
FAST_FINITE = {"nsz", "arcp", "contract", "afn", "reassoc"}
