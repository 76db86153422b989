"""The tests' small, fast PISML configuration: the pipeline end to end in seconds.

One prune round a family (a 40 dB fit 24 s against 37 s with the default three; the rounds' own
tests set their number) and few evaluations in every refinement stage. A pass's time is its window
length (RK4 is sequential in the samples), so the polish runs on shorter windows and the growing
stages take one RK4 step a sample (stop 85, stop 83's machine: a 40 dB fit 32 s -> 22 s; the tests of
those settings set their own). One neural residual (``residual_fits``; its own test sets two): a second
doubles a noisy fit's training and first refinement start.
"""
FAST = {"epochs": 4, "batch_windows": 16, "distill_samples": 2000, "refine_max_nfev": 2, "refine_max_windows": 8,
        "refine_growing_evaluations": "2,2,2", "refine_growing_evaluations_low_snr": "2,2,2,2",
        "refine_polish_evaluations": "2,2", "refine_long_branch_evaluations": 2,
        "refine_polish_windows": "25,50", "refine_growing_substeps": 1, "refine_max_step": 0,
        "refine_prune_rounds": 1, "distill_max_terms": 2,
        "residual_fits": 1}
