#pragma once
// Shared by the command-line tool's tests on bad and hostile input (cli_bad_input_test, cli_hostile_input_test):
// the binaries and config, small well-formed recordings to break, and a folder per test that must hold nothing
// but the inputs afterwards (INTERFACES.md: exit status 1, one clear message on stderr, no partial output).
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "support/command.hpp"

namespace cellbench::test {

inline const std::filesystem::path kCliBin = std::filesystem::path(CELLBENCH_BIN_DIR) / "cellbench";
inline const std::filesystem::path kDaemonBin = std::filesystem::path(CELLBENCH_BIN_DIR) / "cellbenchd";
inline const std::filesystem::path kConfigDir = std::filesystem::path(CELLBENCH_SOURCE_DIR) / "config";
inline const std::filesystem::path kThesisParams = kConfigDir / "cells/p45b-thesis.json";

inline const std::string kGoodBdf =
    "Test Time / s,Voltage / V,Current / A\n0,3.70,0\n1,3.66,-4.5\n2,3.66,-4.5\n3,3.65,-4.5\n4,3.69,0\n";
inline const std::string kGoodNeware =
    "DataPoint,Step Type,Time,Total Time,Current(A),Voltage(V),Capacity(Ah),Energy(Wh),Date,Power(W),Time(s)\n"
    "1,Rest,00:00:00,00:00:00,0.0,4.0964,0.0,0.0,2025-05-23 09:35:38,0.0,0.0\n"
    "2,Rest,00:00:01,00:00:01,0.0,4.0964,0.0,0.0,2025-05-23 09:35:39,0.0,1.0\n";

// Each test gets its own empty folder, named after the test, removed afterwards.
class CliInputFolder : public ::testing::Test {
protected:
    explicit CliInputFolder(std::string prefix) : prefix_(std::move(prefix)) {}

    void SetUp() override {
        dir_ = std::filesystem::temp_directory_path() /
               ("cellbench-" + prefix_ + "-" + std::to_string(::getpid()) + "-" +
                ::testing::UnitTest::GetInstance()->current_test_info()->name());
        std::filesystem::remove_all(dir_);
        std::filesystem::create_directories(dir_);
    }
    void TearDown() override { std::filesystem::remove_all(dir_); }

    // Runs a command line; `output` is its stderr (the contract is about stderr: stdout is the command's report).
    static CommandRun run(const std::string& command) { return run_command(command, 60, Capture::stderr_only); }

    std::filesystem::path write(const std::string& name, const std::string& text) {
        std::ofstream(dir_ / name, std::ios::binary) << text;
        return dir_ / name;
    }
    std::string at(const std::string& name) const { return (dir_ / name).string(); }

    // No file of the folder but the inputs: no output, no temporary file left behind.
    ::testing::AssertionResult only_inputs_left(std::vector<std::string> inputs) const {
        std::vector<std::string> names;
        for (const auto& e : std::filesystem::directory_iterator(dir_)) names.push_back(e.path().filename().string());
        std::sort(names.begin(), names.end());
        std::sort(inputs.begin(), inputs.end());
        if (names == inputs) return ::testing::AssertionSuccess();
        auto f = ::testing::AssertionFailure() << "files left:";
        for (const auto& n : names) f << " " << n;
        return f;
    }

    std::string prefix_;
    std::filesystem::path dir_;
};

}  // namespace cellbench::test
