"""The reconstruction's benchmarks (`hemicube bench ...`, registered by reconstruction.cli), one module a family,
each printing JSON with its device, its seconds per stage and a same-run baseline it checks (twin.bench.same_work,
finish_checks; the command exits non-zero when a check fails):

    reconstruct     bench reconstruct: decode, fine-tuning and fitting of synthetic texels, per 1024^2 sample
    fit             bench fit-forward, bench fit-jacobian: the GGX fit's forward model and Jacobian
    latent          bench latent-ceiling: the best latent against the exact lumitexel, the decoder's ceiling
    limits          bench fit-limits: the fit's errors from exact, decoded and noisy inputs, and the pipeline's
    e2e             bench e2e: `hemicube capture` and `hemicube reconstruct` as users run them
    scaling         bench train-scaling: `hemicube train` under torchrun over 1, 2, ... processes

Each of the last four takes `--tiny` (small sizes on the mini rig, on a CPU), which tests/hemicube/
test_bench_pipeline.py runs; common holds what they share.
"""
