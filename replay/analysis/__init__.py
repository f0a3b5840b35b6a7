"""Analysis over many scenes: statistics, evaluation, sensitivity, calibration, the experiment."""
