"""Light transport at the sample: the anisotropic GGX BRDF, the LED emission profile, the Warp kernels of
paper Eq. 1 (lumitexels) and Eq. 2 (pattern measurements), the public forward API and its torch bridge."""
