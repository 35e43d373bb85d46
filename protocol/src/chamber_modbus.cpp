#include "cellbench/protocol/chamber_modbus.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <limits>

#include <nlohmann/json.hpp>

#include "cellbench/core/recording.hpp"
#include "cellbench/core/json_fields.hpp"
#include "cellbench/protocol/bdf_csv.hpp"  // csv::format_number

namespace cellbench::protocol {

namespace {
using nlohmann::json;

constexpr std::size_t kMaxReadRegisters = 125;  // Modbus limit for functions 3 and 4

// The shared JSON field readers (json_fields.hpp): errors read "SOURCE: JSON.PATH: what was expected".
using json_fields::fail;
using json_fields::finite_number;
using json_fields::member;
using json_fields::string_value;
using json_fields::unsigned_value;

const char* table_name(RegisterTable t) { return t == RegisterTable::holding ? "holding" : "input"; }

const char* type_name(RegisterType t) {
    switch (t) {
        case RegisterType::uint16: return "uint16";
        case RegisterType::int16: return "int16";
        case RegisterType::uint32: return "uint32";
        case RegisterType::int32: return "int32";
        case RegisterType::float32: return "float32";
    }
    return "?";
}

RegisterTable table_of(const json& j, const std::string& source, const std::string& path) {
    const std::string s = string_value(j, source, path);
    if (s == "holding") return RegisterTable::holding;
    if (s == "input") return RegisterTable::input;
    fail(source, path, "expected \"holding\" or \"input\", got \"" + s + "\"");
}

RegisterValueSpec value_spec_of(const json& j, const std::string& source, const std::string& path) {
    RegisterValueSpec v;
    v.address = static_cast<std::uint16_t>(unsigned_value(member(j, "address", source, path), 0xFFFF, source, path + ".address"));
    if (j.contains("table")) v.table = table_of(j["table"], source, path + ".table");
    if (j.contains("type")) {
        const std::string t = string_value(j["type"], source, path + ".type");
        bool known = false;
        for (auto candidate : {RegisterType::uint16, RegisterType::int16, RegisterType::uint32, RegisterType::int32,
                               RegisterType::float32})
            if (t == type_name(candidate)) {
                v.type = candidate;
                known = true;
            }
        if (!known) fail(source, path + ".type", "expected uint16, int16, uint32, int32 or float32, got \"" + t + "\"");
    }
    if (j.contains("word_order")) {
        const std::string w = string_value(j["word_order"], source, path + ".word_order");
        if (w == "high_first") v.word_order = WordOrder::high_word_first;
        else if (w == "low_first") v.word_order = WordOrder::low_word_first;
        else fail(source, path + ".word_order", "expected \"high_first\" or \"low_first\", got \"" + w + "\"");
    }
    if (j.contains("scale")) v.scale = finite_number(j["scale"], source, path + ".scale");
    if (j.contains("offset")) v.offset = finite_number(j["offset"], source, path + ".offset");
    return v;
}

json value_spec_json(const RegisterValueSpec& v) {
    return {{"table", table_name(v.table)}, {"address", v.address}, {"type", type_name(v.type)},
            {"word_order", v.word_order == WordOrder::high_word_first ? "high_first" : "low_first"},
            {"scale", v.scale}, {"offset", v.offset}};
}

// Raw 32-bit quantity from two registers in the spec's word order.
std::uint32_t raw32(const RegisterValueSpec& spec, const std::uint16_t* r) {
    const std::uint32_t hi = spec.word_order == WordOrder::high_word_first ? r[0] : r[1];
    const std::uint32_t lo = spec.word_order == WordOrder::high_word_first ? r[1] : r[0];
    return hi << 16 | lo;
}

// Raw range of a type (float32: its finite range).
std::pair<double, double> raw_range(RegisterType t) {
    switch (t) {
        case RegisterType::uint16: return {0.0, 65535.0};
        case RegisterType::int16: return {-32768.0, 32767.0};
        case RegisterType::uint32: return {0.0, 4294967295.0};
        case RegisterType::int32: return {-2147483648.0, 2147483647.0};
        case RegisterType::float32: return {-std::numeric_limits<float>::max(), std::numeric_limits<float>::max()};
    }
    return {0.0, 0.0};
}

struct Item {
    RegisterTable table;
    std::uint16_t address;
    std::size_t count;
    const char* what;
};

std::vector<Item> items_of(const ChamberRegisterMap& m) {
    std::vector<Item> items{{m.process_value.table, m.process_value.address, m.process_value.width_registers(), "process_value"},
                            {m.setpoint.table, m.setpoint.address, m.setpoint.width_registers(), "setpoint"},
                            {RegisterTable::holding, m.run.address, 1, "run"}};
    if (m.alarms) items.push_back({m.alarms->table, m.alarms->address, 1, "alarms"});
    return items;
}

}  // namespace

std::size_t RegisterValueSpec::width_registers() const {
    return type == RegisterType::uint16 || type == RegisterType::int16 ? 1 : 2;
}

const std::uint16_t* RegisterBlock::find(RegisterTable t, std::uint16_t address, std::size_t count) const {
    if (t != table || address < start) return nullptr;
    const std::size_t offset = address - start;
    if (offset + count > values.size()) return nullptr;
    return values.data() + offset;
}

std::uint16_t* RegisterBlock::find(RegisterTable t, std::uint16_t address, std::size_t count) {
    return const_cast<std::uint16_t*>(std::as_const(*this).find(t, address, count));
}

std::optional<double> decode_register_value(const RegisterValueSpec& spec, const std::uint16_t* r) {
    double raw = 0.0;
    switch (spec.type) {
        case RegisterType::uint16: raw = r[0]; break;
        case RegisterType::int16: raw = static_cast<std::int16_t>(r[0]); break;
        case RegisterType::uint32: raw = raw32(spec, r); break;
        case RegisterType::int32: raw = static_cast<std::int32_t>(raw32(spec, r)); break;
        case RegisterType::float32: raw = std::bit_cast<float>(raw32(spec, r)); break;
    }
    const double v = raw * spec.scale + spec.offset;
    if (!std::isfinite(v)) return std::nullopt;
    return v;
}

std::optional<std::vector<std::uint16_t>> encode_register_value(const RegisterValueSpec& spec, double value) {
    if (!std::isfinite(value) || spec.scale == 0.0) return std::nullopt;
    double raw = (value - spec.offset) / spec.scale;
    if (spec.type != RegisterType::float32) raw = std::nearbyint(raw);
    const auto [lo, hi] = raw_range(spec.type);
    if (!(raw >= lo && raw <= hi)) return std::nullopt;
    std::uint32_t bits = 0;
    switch (spec.type) {
        case RegisterType::uint16:
        case RegisterType::uint32: bits = static_cast<std::uint32_t>(raw); break;
        case RegisterType::int16:
        case RegisterType::int32: bits = static_cast<std::uint32_t>(static_cast<std::int32_t>(raw)); break;
        case RegisterType::float32: bits = std::bit_cast<std::uint32_t>(static_cast<float>(raw)); break;
    }
    if (spec.width_registers() == 1) return std::vector<std::uint16_t>{static_cast<std::uint16_t>(bits)};
    const auto high = static_cast<std::uint16_t>(bits >> 16), low = static_cast<std::uint16_t>(bits);
    if (spec.word_order == WordOrder::high_word_first) return std::vector<std::uint16_t>{high, low};
    return std::vector<std::uint16_t>{low, high};
}

ChamberRegisterMap ChamberRegisterMap::bench_default() {
    ChamberRegisterMap m;
    m.alarms = AlarmSpec{RegisterTable::holding, 11,
                         {{"high_temperature", 0}, {"low_temperature", 1}, {"heater_fault", 2}, {"cooling_fault", 3},
                          {"door_open", 4}}};
    return m;
}

ChamberRegisterMap ChamberRegisterMap::from_json(const json& j, const std::string& source) {
    if (!j.is_object()) fail(source, "$", "expected a JSON object");
    if (j.contains("schema") && j["schema"] != kChamberModbusSchema)
        fail(source, "$.schema", std::string("expected \"") + kChamberModbusSchema + "\"");
    ChamberRegisterMap m;
    m.process_value = value_spec_of(member(j, "process_value", source, "$"), source, "$.process_value");
    m.setpoint = value_spec_of(member(j, "setpoint", source, "$"), source, "$.setpoint");
    const json& run = member(j, "run", source, "$");
    m.run.address = static_cast<std::uint16_t>(unsigned_value(member(run, "address", source, "$.run"), 0xFFFF, source, "$.run.address"));
    if (run.contains("table") && table_of(run["table"], source, "$.run.table") != RegisterTable::holding)
        fail(source, "$.run.table", "expected \"holding\" (run/stop is written)");
    if (run.contains("run_value"))
        m.run.run_value = static_cast<std::uint16_t>(unsigned_value(run["run_value"], 0xFFFF, source, "$.run.run_value"));
    if (run.contains("stop_value"))
        m.run.stop_value = static_cast<std::uint16_t>(unsigned_value(run["stop_value"], 0xFFFF, source, "$.run.stop_value"));
    if (j.contains("alarms")) {
        const json& a = j["alarms"];
        AlarmSpec spec;
        spec.address = static_cast<std::uint16_t>(unsigned_value(member(a, "address", source, "$.alarms"), 0xFFFF, source, "$.alarms.address"));
        if (a.contains("table")) spec.table = table_of(a["table"], source, "$.alarms.table");
        const json& bits = member(a, "bits", source, "$.alarms");
        if (!bits.is_object()) fail(source, "$.alarms.bits", "expected an object of alarm name -> bit 0..15");
        for (const auto& [name, bit] : bits.items())
            spec.bits.emplace_back(name, static_cast<unsigned>(unsigned_value(bit, 15, source, "$.alarms.bits." + name)));
        std::sort(spec.bits.begin(), spec.bits.end(), [](const auto& x, const auto& y) { return x.second < y.second; });
        m.alarms = std::move(spec);
    }
    if (j.contains("setpoint_range_c")) {
        const json& r = j["setpoint_range_c"];
        if (!r.is_array() || r.size() != 2) fail(source, "$.setpoint_range_c", "expected [min, max] in degC");
        m.setpoint_min_c = finite_number(r[0], source, "$.setpoint_range_c[0]");
        m.setpoint_max_c = finite_number(r[1], source, "$.setpoint_range_c[1]");
    }
    m.validate(source);
    return m;
}

json ChamberRegisterMap::to_json() const {
    json j = {{"schema", kChamberModbusSchema},
              {"process_value", value_spec_json(process_value)},
              {"setpoint", value_spec_json(setpoint)},
              {"run", {{"table", "holding"}, {"address", run.address}, {"run_value", run.run_value}, {"stop_value", run.stop_value}}},
              {"setpoint_range_c", {setpoint_min_c, setpoint_max_c}}};
    if (alarms) {
        json bits = json::object();
        for (const auto& [name, bit] : alarms->bits) bits[name] = bit;
        j["alarms"] = {{"table", table_name(alarms->table)}, {"address", alarms->address}, {"bits", bits}};
    }
    return j;
}

void ChamberRegisterMap::validate(const std::string& source) const {
    for (const auto& [spec, path] : {std::pair{&process_value, "$.process_value"}, {&setpoint, "$.setpoint"}}) {
        if (spec->scale == 0.0 || !std::isfinite(spec->scale)) fail(source, std::string(path) + ".scale", "expected a finite non-zero number");
        if (!std::isfinite(spec->offset)) fail(source, std::string(path) + ".offset", "expected a finite number");
        if (spec->address + spec->width_registers() > 0x10000) fail(source, std::string(path) + ".address", "register beyond 65535");
    }
    if (setpoint.table != RegisterTable::holding) fail(source, "$.setpoint.table", "expected \"holding\" (the set point is written)");
    if (run.run_value == run.stop_value) fail(source, "$.run", "run_value and stop_value must differ");
    if (!(setpoint_min_c < setpoint_max_c)) fail(source, "$.setpoint_range_c", "expected min < max");
    for (const double limit : {setpoint_min_c, setpoint_max_c})
        if (!encode_register_value(setpoint, limit))
            fail(source, "$.setpoint_range_c", "the set point register cannot represent " + csv::format_number(limit) + " degC");
    if (alarms) {
        for (std::size_t i = 0; i < alarms->bits.size(); ++i) {
            if (alarms->bits[i].second > 15) fail(source, "$.alarms.bits." + alarms->bits[i].first, "expected a bit 0..15");
            for (std::size_t k = 0; k < i; ++k)
                if (alarms->bits[k].second == alarms->bits[i].second || alarms->bits[k].first == alarms->bits[i].first)
                    fail(source, "$.alarms.bits." + alarms->bits[i].first, "bit or name used twice");
        }
    }
    const auto items = items_of(*this);
    for (std::size_t i = 0; i < items.size(); ++i)
        for (std::size_t k = 0; k < i; ++k) {
            const auto& a = items[i];
            const auto& b = items[k];
            if (a.table == b.table && a.address < b.address + b.count && b.address < a.address + a.count)
                fail(source, std::string("$.") + a.what + ".address",
                     std::string("overlaps the registers of ") + b.what);
        }
}

std::optional<std::vector<std::uint16_t>> ChamberRegisterMap::encode_setpoint(double setpoint_c) const {
    if (!std::isfinite(setpoint_c) || setpoint_c < setpoint_min_c || setpoint_c > setpoint_max_c) return std::nullopt;
    return encode_register_value(setpoint, setpoint_c);
}

std::vector<RegisterRange> ChamberRegisterMap::read_plan() const {
    auto items = items_of(*this);
    std::sort(items.begin(), items.end(), [](const Item& a, const Item& b) {
        return a.table != b.table ? a.table < b.table : a.address < b.address;
    });
    std::vector<RegisterRange> plan;
    for (const auto& item : items) {
        const std::size_t end = item.address + item.count;
        if (!plan.empty() && plan.back().table == item.table &&
            end - plan.back().start <= kMaxReadRegisters) {
            plan.back().count = static_cast<std::uint16_t>(std::max<std::size_t>(plan.back().count, end - plan.back().start));
        } else {
            plan.push_back({item.table, item.address, static_cast<std::uint16_t>(item.count)});
        }
    }
    return plan;
}

std::vector<std::string> ChamberRegisterMap::alarm_names(std::uint16_t word) const {
    std::vector<std::string> names;
    if (!alarms) return names;
    for (const auto& [name, bit] : alarms->bits)
        if (word & (1u << bit)) names.push_back(name);
    return names;
}

std::optional<unsigned> ChamberRegisterMap::alarm_bit(const std::string& name) const {
    if (alarms)
        for (const auto& [n, bit] : alarms->bits)
            if (n == name) return bit;
    return std::nullopt;
}

std::optional<ChamberRegisterState> ChamberRegisterMap::decode(std::span<const RegisterBlock> blocks,
                                                               std::string* error) const {
    auto find = [&](RegisterTable t, std::uint16_t address, std::size_t count) -> const std::uint16_t* {
        for (const auto& b : blocks)
            if (const auto* p = b.find(t, address, count)) return p;
        return nullptr;
    };
    auto failed = [&](std::string what) -> std::optional<ChamberRegisterState> {
        if (error) *error = std::move(what);
        return std::nullopt;
    };
    ChamberRegisterState s;
    const auto* pv = find(process_value.table, process_value.address, process_value.width_registers());
    const auto* sp = find(setpoint.table, setpoint.address, setpoint.width_registers());
    const auto* run_reg = find(RegisterTable::holding, run.address, 1);
    if (!pv) return failed("process value register " + std::to_string(process_value.address) + " not read");
    if (!sp) return failed("set point register " + std::to_string(setpoint.address) + " not read");
    if (!run_reg) return failed("run/stop register " + std::to_string(run.address) + " not read");
    const auto pv_c = decode_register_value(process_value, pv);
    if (!pv_c) return failed("process value is not a finite number");
    const auto sp_c = decode_register_value(setpoint, sp);
    if (!sp_c) return failed("set point is not a finite number");
    s.process_value_c = *pv_c;
    s.setpoint_c = *sp_c;
    if (*run_reg == run.run_value) s.running = true;
    else if (*run_reg == run.stop_value) s.running = false;
    if (alarms) {
        const auto* a = find(alarms->table, alarms->address, 1);
        if (!a) return failed("alarm register " + std::to_string(alarms->address) + " not read");
        s.alarm_word = *a;
        s.active_alarms = alarm_names(*a);
    }
    return s;
}

ChamberWriteResult ChamberRegisterMap::apply_write(RegisterBlock& holding, std::uint16_t address,
                                                   std::span<const std::uint16_t> values) const {
    ChamberWriteResult result;
    auto reject = [&](std::uint8_t code, std::string reason) {
        result = {};
        result.exception_code = code;
        result.reason = std::move(reason);
        return result;
    };
    if (values.empty() || address + values.size() > 0x10000) return reject(2, "empty or out-of-range write");
    const std::size_t sp_width = setpoint.width_registers();
    bool touches_setpoint = false, touches_run = false;
    for (std::size_t i = 0; i < values.size(); ++i) {
        const std::size_t a = address + i;
        const bool in_sp = a >= setpoint.address && a < setpoint.address + sp_width;
        const bool in_run = a == run.address;
        if (!in_sp && !in_run) return reject(2, "register " + std::to_string(a) + " is not writable");
        touches_setpoint |= in_sp;
        touches_run |= in_run;
    }
    if (!holding.find(RegisterTable::holding, address, values.size()) ||
        (touches_setpoint && !holding.find(RegisterTable::holding, setpoint.address, sp_width)))
        return reject(2, "register outside the holding image");

    // Check on a copy, commit only when everything is valid.
    RegisterBlock next = holding;
    std::copy(values.begin(), values.end(), next.find(RegisterTable::holding, address, values.size()));
    if (touches_setpoint) {
        const auto sp = decode_register_value(setpoint, next.find(RegisterTable::holding, setpoint.address, sp_width));
        if (!sp || *sp < setpoint_min_c || *sp > setpoint_max_c)
            return reject(3, "set point outside " + csv::format_number(setpoint_min_c) + ".." + csv::format_number(setpoint_max_c) + " degC");
        result.setpoint_c = sp;
    }
    if (touches_run) {
        const std::uint16_t v = *next.find(RegisterTable::holding, run.address, 1);
        if (v != run.run_value && v != run.stop_value) return reject(3, "run/stop value " + std::to_string(v) + " is neither run nor stop");
        result.running = v == run.run_value;
    }
    holding = std::move(next);
    return result;
}

}  // namespace cellbench::protocol
