"""The names a fit request may use, without the engine (the config reader checks
them before JAX is imported). Each registry asserts at import that it implements
exactly these names."""

#: Solvers of ``fitter.fit._solvers``, the default first.
SOLVERS = ("levenberg_marquardt", "dogleg", "gauss_newton", "bfgs", "adam")
#: Residual losses of ``fitter.fit._problem``.
LOSSES = ("l2", "huber", "cauchy")
