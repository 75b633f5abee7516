"""The command line, configs, outputs and the experiment runner."""
