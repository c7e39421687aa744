"""NumPy twins of the Warp kernels: same names, slow and obvious. The truth the parity tests compare to."""
