#include <cstdio>
#include <filesystem>

#include <spdlog/spdlog.h>

#include "cellbench/estimator/generate.hpp"
#include "cellbench/protocol/bdf_csv.hpp"
#include "cli/commands.hpp"
#include "cli/files.hpp"

namespace cellbench::cli {

int run_generate(const GenerateOptions& o) {
    const auto base = load_params(o.base);
    estimator::GeneratorOptions g;
    g.seed = o.seed;
    g.hidden_effect = o.effect == "none" ? "" : o.effect;
    g.magnitude = o.magnitude;
    const auto c = estimator::generate_case(base, g);
    const std::filesystem::path dir = o.output_dir;
    std::error_code ec;
    std::filesystem::create_directories(dir, ec);
    if (ec) throw InputError(o.output_dir + ": cannot create the folder: " + ec.message());
    write_file_atomic(dir / "characterization.bdf.csv", [&](std::ostream& out) { protocol::write_bdf_csv(out, c.characterization); });
    write_file_atomic(dir / "validation.bdf.csv", [&](std::ostream& out) { protocol::write_bdf_csv(out, c.validation); });
    nlohmann::json truth = c.truth;
    truth["characterization_params"] = c.truth_characterization.to_json();
    truth["validation_params"] = c.truth_validation.to_json();
    write_json_file(dir / "truth.json", truth);
    std::printf("wrote %s/{characterization,validation}.bdf.csv (%zu and %zu rows) and truth.json (hidden: %s)\n",
                o.output_dir.c_str(), c.characterization.size(), c.validation.size(),
                g.hidden_effect.empty() ? "nothing" : g.hidden_effect.c_str());
    return 0;
}

}  // namespace cellbench::cli
