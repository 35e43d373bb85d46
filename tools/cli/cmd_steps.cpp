// `cellbench steps --program NAME --cell CELL [--config BENCH] -o FILE.xml`: the step file the daemon would
// send to the Neware tester for that program, in the real BTS Client schema (protocol/neware_stepfile.hpp).
//
// A program with several cycler segments (e.g. one per chamber temperature) gives one file per segment:
// FILE.xml for the first, FILE-2.xml, FILE-3.xml, ... for the others. A capacity limit that refers to other
// steps (thesis eq. 2.4) is written resolved with the cell's nominal capacity; the daemon resolves it with the
// measured capacity instead (it runs such a program as two step files, see tester_parts), which is said on
// stderr.
#include <cstdio>
#include <filesystem>

#include <spdlog/spdlog.h>

#include "cellbench/core/recording.hpp"
#include "cellbench/daemon/config.hpp"
#include "cellbench/protocol/neware_stepfile.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"

namespace cellbench::cli {

int run_steps(const StepsOptions& o) {
    const auto bench = daemon::load_bench_config(o.config);
    const auto cell = daemon::load_cell_config(daemon::cell_file(bench.config_dir, o.cell));
    const auto program = daemon::load_program(daemon::program_file(bench.config_dir, o.program), cell, {}, &bench);
    std::vector<protocol::StepProgram> files;
    for (const auto& segment : program.segments)
        if (const auto* c = std::get_if<daemon::CyclerSegment>(&segment)) files.push_back(c->program);
    if (files.empty()) throw InputError("program " + o.program + ": no cycler segment, so no step file");
    const std::filesystem::path out(o.output);
    for (std::size_t i = 0; i < files.size(); ++i) {
        protocol::StepProgram p = files[i];
        p.settings.nominal_capacity_ah = cell.nominal_capacity_ah;  // MultCap: the reference of C-rates
        for (std::size_t k = 0; k < p.steps.size(); ++k) {
            const auto& limit = p.steps[k].cutoff_capacity_ah;
            if (limit && !limit->is_constant())
                std::fprintf(stderr,
                             "step %zu: capacity limit %s written with nominal capacities (%.4g Ah cell); the daemon "
                             "writes it from the measured ones when the program runs\n",
                             k + 1, limit->to_string().c_str(), cell.nominal_capacity_ah);
        }
        const std::string xml = protocol::compile_step_file(p);
        std::filesystem::path path = out;
        if (i > 0) path = out.parent_path() / (out.stem().string() + "-" + std::to_string(i + 1) + out.extension().string());
        write_file_atomic(path, [&](std::ostream& os) { os << xml; });
        std::printf("%s: %s, %zu steps\n", path.string().c_str(), p.name.c_str(), p.steps.size());
    }
    return 0;
}

}  // namespace cellbench::cli
