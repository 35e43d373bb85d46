#include "neware_xml.hpp"

#include <exception>
#include <sstream>

#include <boost/property_tree/xml_parser.hpp>

#include "cellbench/protocol/neware_bts.hpp"

namespace cellbench::protocol::neware::xml {

namespace pt = boost::property_tree;

void append_escaped(std::string& out, std::string_view text, Escape extra) {
    for (const char c : text) {
        switch (c) {
            case '&': out += "&amp;"; continue;
            case '<': out += "&lt;"; continue;
            case '>': out += "&gt;"; continue;
            case '"': out += "&quot;"; continue;
            default: break;
        }
        if (extra == Escape::apostrophe && c == '\'') {
            out += "&apos;";
        } else if (extra == Escape::whitespace && (c == '\n' || c == '\r' || c == '\t')) {
            out += c == '\n' ? "&#10;" : c == '\r' ? "&#13;" : "&#9;";
        } else {
            out += c;
        }
    }
}

pt::ptree read_document(std::string_view xml, const std::string& context) {
    pt::ptree tree;
    std::istringstream in(normalize_vendor_xml(xml));  // (its ProtocolError is not a parse error: not wrapped)
    try {
        pt::read_xml(in, tree, pt::xml_parser::no_comments);
    } catch (const pt::xml_parser_error& e) {
        throw ProtocolError(context + "malformed XML: " + e.message() + " (line " + std::to_string(e.line()) + ")");
    } catch (const std::exception& e) {
        throw ProtocolError(context + "malformed XML: " + e.what());
    }
    return tree;
}

}  // namespace cellbench::protocol::neware::xml
