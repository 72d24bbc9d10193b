"""numba kernels: arrays and scalars in, arrays out. Public wrappers check inputs."""
