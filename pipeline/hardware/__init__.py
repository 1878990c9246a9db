"""The hardware edge that is not a stage: the NI DAQ (lens staircase and camera trigger),
its pure waveforms, the ``[camera]``/``[daq]`` configuration and the scan planner."""
