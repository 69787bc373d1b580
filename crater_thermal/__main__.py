from crater_thermal.cli import main

main()
