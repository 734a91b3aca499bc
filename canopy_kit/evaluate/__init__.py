"""Everything that scores a run: against the simulator's truth (segmentation, volumes, the
mapping), agreement statistics, and the checks a run passes or fails without truth."""
