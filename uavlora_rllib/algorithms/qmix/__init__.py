"""QMIX (monotonic mixer on the global state) and VDN (sum mixer) with recurrent agent Q-networks."""
