"""The pipeline around the stages: the runtime (stages, bounded queues, sinks), the
configuration and message models, the scan plan, the wiring of a configuration into a
running pipeline and the frame feeds; :mod:`.cli`, :mod:`.formats`, :mod:`.hardware` and
:mod:`.metrology` hold the command line, the file formats, the hardware edge and the
metrology."""
