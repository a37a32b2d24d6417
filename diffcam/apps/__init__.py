"""What runs the library end to end: the command line (:mod:`.cli`), the demo
(:mod:`.demo`) and the paper's experiments (:mod:`.paper`)."""
