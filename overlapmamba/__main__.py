from overlapmamba.cli import main

main()
