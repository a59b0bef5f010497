"""What a run or a study keeps on disk: its Orbax checkpoints and the files it writes whole
(`checkpoints`), the log of every body it evaluates with the rule for its best bodies
(`bodylog`), and trained controllers saved with their bodies (`saved_controllers`)."""
