// cellbench: offline analysis of battery-cell recordings and client of the cellbenchd daemon.
#include "cli/commands.hpp"

int main(int argc, char** argv) { return cellbench::cli::run_cli(argc, argv); }
