// cellbench_plant: synthetic recordings with known truth from the independent validation plant.
#include <chrono>
#include <cstdio>
#include <exception>
#include <filesystem>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <spdlog/spdlog.h>

#include "cellbench/plant/plant.hpp"

int main(int argc, char** argv) {
    namespace plant = cellbench::plant;
    CLI::App app{"Independent validation plant: writes hppc.bdf.csv, cc_low.bdf.csv, cc_high.bdf.csv, drive.bdf.csv and "
                 "truth.json for one synthetic cell (issues 11 and 13)"};
    std::uint64_t seed = 1;
    std::string layout = "thesis";
    std::vector<std::string> effects;
    double sample_s = 0.0;
    std::string out_dir;
    bool temperature_dependence = false, current_dependence = false, no_noise = false;
    app.add_option("--seed", seed, "cell, profile and noise seed")->required();
    app.add_option("--layout", layout, "HPPC layout")->check(CLI::IsMember({"thesis", "usabc", "multi", "random", "gitt"}));
    app.add_option("--effect", effects, "hidden effect id (repeatable, INTERFACES.md ids or none)");
    app.add_option("--sample-s", sample_s, "sampling interval around pulses and in the drive (default: by seed, 0.1-1 s)")
        ->check(CLI::Range(0.01, 10.0));
    app.add_flag("--temperature-dependence", temperature_dependence, "base cell with temperature-dependent resistances");
    app.add_flag("--current-dependence", current_dependence, "base cell with a current-dependent RC1 overpotential");
    app.add_flag("--no-noise", no_noise, "write the exact values (no noise, no quantization)");
    double thesis_pulse_s = 30.0;
    app.add_option("--thesis-discharge-pulse-s", thesis_pulse_s, "thesis layout: discharge pulse length (Table 2.12: 30 s)")
        ->check(CLI::Range(1.0, 600.0));
    bool second_drive = false;
    app.add_flag("--second-drive", second_drive,
                 "also write drive2.bdf.csv: another drive of the same cell and bench set-up (to confirm a diagnosis on)");
    double capacity_ah = 0.0;
    app.add_option("--capacity-ah", capacity_ah,
                   "another cell size: the seed's cell scaled to this capacity (resistances 1/f, C_th f, area and R_th "
                   "f^(2/3); e.g. 60 for a pouch cell)")
        ->check(CLI::Range(0.1, 2000.0));
    std::vector<double> record_conditions;
    app.add_option("--log-on-change", record_conditions,
                   "write only the rows a cycler's record conditions keep: DV_V DI_A DT_S (a row at each step's start and "
                   "end, and when the voltage moved by DV_V, the current by DI_A or DT_S passed; e.g. 0.005 0.05 60)")
        ->expected(3);
    app.add_option("-o,--output", out_dir, "output directory (created)")->required();
    CLI11_PARSE(app, argc, argv);

    try {
        plant::PlantOptions o;
        o.seed = seed;
        o.layout = *plant::parse_layout(layout);
        for (const auto& id : effects) {
            auto e = plant::parse_effect(id);
            if (!e) {
                std::fprintf(stderr, "cellbench_plant: unknown effect id '%s'\n", id.c_str());
                return 2;
            }
            o.effects.push_back(*e);
        }
        if (sample_s > 0.0) o.sample_s = sample_s;
        o.temperature_dependence = temperature_dependence;
        o.current_dependence = current_dependence;
        o.noise = !no_noise;
        o.thesis_discharge_pulse_s = thesis_pulse_s;
        if (capacity_ah > 0.0) o.capacity_ah = capacity_ah;

        const std::filesystem::path dir(out_dir);
        std::filesystem::create_directories(dir);
        const auto cell = plant::make_cell(o);
        const auto truth = plant::make_truth(cell, o.layout);
        struct Job {
            const char* file;
            plant::Recording (*make)(const plant::CellSpec&, const plant::PlantOptions&);
        };
        const Job jobs[] = {{"hppc.bdf.csv", plant::generate_hppc},
                            {"cc_low.bdf.csv", plant::generate_cc_low},
                            {"cc_high.bdf.csv", plant::generate_cc_high},
                            {"drive.bdf.csv", plant::generate_drive}};
        std::vector<Job> todo(std::begin(jobs), std::end(jobs));
        if (second_drive) todo.push_back({"drive2.bdf.csv", plant::generate_second_drive});
        for (const auto& job : todo) {
            const auto t0 = std::chrono::steady_clock::now();
            auto rec = job.make(cell, o);
            if (!record_conditions.empty())
                rec = plant::log_on_change(rec, {record_conditions[0], record_conditions[1], record_conditions[2]});
            const double gen_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
            plant::write_bdf_csv(rec, dir / job.file);
            std::printf("wrote %s: %zu rows, %.2f h of bench time, %zu steps (generated in %.3f s)\n",
                        (dir / job.file).c_str(), rec.size(), rec.time_s.empty() ? 0.0 : rec.time_s.back() / 3600.0,
                        rec.steps.size(), gen_s);
        }
        plant::write_truth_json(truth, dir / "truth.json");
        if (o.layout == plant::Layout::random) {
            const auto l = plant::draw_random_layout(seed, cell.measurement.sample_s);
            std::printf("random layout: %s%s, SOC step %.0f %% at %.2gC, %.0f s rest after it; discharge pulse %.0f s at %.2fC, "
                        "charge pulse %.0f s at %.2fC%s, %.0f s rest between, %.0f s after, %d current(s) per level\n",
                        l.upward ? "upward from empty" : "downward from full", l.pilot ? ", pilot discharge" : "",
                        100 * l.soc_step, l.step_rate_c, l.rest_after_step_s, l.discharge_pulse_s, l.discharge_rate_c,
                        l.charge_pulse_s, l.charge_rate_c, l.charge_first ? " (first)" : "", l.rest_between_s,
                        l.rest_after_pulses_s, l.currents_per_level);
        }
        if (o.layout == plant::Layout::gitt) {
            const auto l = plant::draw_gitt_layout(seed);
            std::printf("gitt layout: steps of %.0f %% at %.2gC, %.0f s rest after each, %s\n", 100 * l.soc_step, l.rate_c,
                        l.rest_s, l.upward ? "down to the cut-off and back up" : "down to the cut-off");
        }
        std::printf("wrote %s: seed %llu, %s %s, %.4f Ah, layout %s, sampling %.3g s, effects [", (dir / "truth.json").c_str(),
                    static_cast<unsigned long long>(seed), truth.chemistry.c_str(), truth.format.c_str(), truth.capacity_ah,
                    truth.layout.c_str(), cell.measurement.sample_s);
        for (std::size_t k = 0; k < truth.effects.size(); ++k)
            std::printf("%s%s", k ? ", " : "", truth.effects[k].c_str());
        std::printf("]\n");
    } catch (const std::exception& e) {
        spdlog::error("cellbench_plant: {}", e.what());
        return 1;
    }
    return 0;
}
