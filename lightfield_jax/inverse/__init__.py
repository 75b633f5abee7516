"""The inverse pipeline: separation, decay fit, basin scan, joint fit, trust
(noise, error budget, verdict), model size."""
