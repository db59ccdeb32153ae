from toptag.cli import main

main()
