"""The drift models, each a streaming model with ``step`` and ``run``: the polynomial baseline, the wavelet
echo-state network and the PSO-SVR comparator (fitting them: ``compensation.fitting``)."""
