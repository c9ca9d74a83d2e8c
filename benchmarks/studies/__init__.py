"""Studies: experiments on what a model or the data does (training ladders, fitting, thresholds, label and rendering
analyses, int8 sensitivity), each printing its tables and, where it trains, writing its records as JSON lines as
they come. Run as ``python -m benchmarks.studies.NAME --help``."""
