"""The run command, `python -m evojax_morph.run` (`cli`, its `process`): a run by stages, the
outer loop with its checkpoints and body log (`driver`), later programs lowered on a second
thread (`compile_ahead`), the best bodies measured again and the run's best chosen
(`confirm_stage`), the summary with its plots and video (`report`). The library's services it
calls live apart: `search` (`pipeline`, `study`, `confirm`), `records` (`checkpoints`,
`bodylog`, `saved_controllers`) and `figures` (`plots`, `video`)."""
