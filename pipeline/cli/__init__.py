"""The ``sffscan`` command line: :mod:`.main` builds the parser; one module per group of
commands (:mod:`.record`, :mod:`.hardware`, :mod:`.calibrate`, :mod:`.metrology`) adds its
sub-commands; :mod:`.common` holds what they share."""
