"""QMIX (monotonic mixer on the global state) and VDN (sum mixer, plus a state value V(s) by default: VDN-S) with recurrent agent Q-networks."""
