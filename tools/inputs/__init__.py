"""Reading the files a user hands the commands, strictly (``infile``): configuration
(``userconfig``), calibration (``calibfile``) and sweep outputs (``sweepfile``)."""
