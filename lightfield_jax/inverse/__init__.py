"""The inverse pipeline: separation, decay fit, basin scan, joint fit, trust, model size."""
