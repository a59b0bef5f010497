"""The run command, `python -m evojax_morph.run` (`cli`, its flags in `options`): a run as
stages that hand values to each other (`driver`): where it starts (`resume`), then `stages`:
the steps (`Evolve`), the best bodies measured again and the run's best chosen (`Confirm`), the
summary with its plots and video (`Report`; what it says: `report`); one writer of its files
(`recorder`); later programs lowered on a second thread (`compile_ahead`). The library's
services it calls live apart: `search` (`pipeline`, `study`, `confirm`), `records`
(`checkpoints`, `bodylog`, `saved_controllers`) and `figures` (`plots`, `video`)."""
