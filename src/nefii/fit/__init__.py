"""The NeFII joint optimisation: path tracing with the radiance cache, losses, policies, trainer."""
